"""MJCF models of the DeepMind Control walker and cheetah, written for this project.

The bodies, geoms, joints, actuators, masses, inertias and options reproduce the
dm_control suite models (``suite/walker.xml`` and ``suite/cheetah.xml``, dm_control
1.0.50); ``tests/test_envs_dm_control.py`` checks the compiled models field by field
against dm_control. Visual-only assets (skybox, textures, headlight) are reduced to
the materials' colours, which the ray-cast camera uses.
"""

from __future__ import annotations

import mujoco

_MATERIALS = """
  <visual>
    <headlight ambient=".4 .4 .4" diffuse=".8 .8 .8" specular="0.1 0.1 0.1"/>
    <map znear=".01"/>
    <quality shadowsize="2048"/>
  </visual>
  <asset>
    <texture name="skybox" type="skybox" builtin="gradient" rgb1=".4 .6 .8" rgb2="0 0 0"
             width="800" height="800" mark="random" markrgb="1 1 1"/>
    <texture name="grid" type="2d" builtin="checker" rgb1=".1 .2 .3" rgb2=".2 .3 .4" width="300" height="300"
             mark="edge" markrgb=".2 .3 .4"/>
    <material name="grid" texture="grid" texrepeat="1 1" texuniform="true" reflectance=".2"/>
    <material name="self" rgba=".7 .5 .3 1"/>
  </asset>
"""

WALKER_XML = f"""
<mujoco model="planar walker">
{_MATERIALS}
  <option timestep="0.0025"/>
  <statistic extent="2" center="0 0 1"/>
  <default>
    <joint damping=".1" armature="0.01" limited="true" solimplimit="0 .99 .01"/>
    <geom contype="1" conaffinity="0" friction=".7 .1 .1"/>
    <motor ctrlrange="-1 1" ctrllimited="true"/>
    <default class="walker">
      <geom material="self" type="capsule"/>
      <joint axis="0 -1 0"/>
    </default>
  </default>
  <worldbody>
    <geom name="floor" type="plane" conaffinity="1" pos="248 0 0" size="250 .8 .2"
          material="grid" zaxis="0 0 1"/>
    <body name="torso" pos="0 0 1.3" childclass="walker">
      <light name="light" pos="0 0 2" mode="trackcom"/>
      <camera name="side" pos="0 -2 .7" euler="60 0 0" mode="trackcom"/>
      <joint name="rootz" axis="0 0 1" type="slide" limited="false" armature="0" damping="0"/>
      <joint name="rootx" axis="1 0 0" type="slide" limited="false" armature="0" damping="0"/>
      <joint name="rooty" axis="0 1 0" type="hinge" limited="false" armature="0" damping="0"/>
      <geom name="torso" size="0.07 0.3"/>
{{legs}}
    </body>
  </worldbody>
  <sensor>
    <subtreelinvel name="torso_subtreelinvel" body="torso"/>
  </sensor>
  <actuator>
{{motors}}
  </actuator>
</mujoco>
"""

_WALKER_LEG = """
      <body name="{side}_thigh" pos="0 {y} -0.3">
        <joint name="{side}_hip" range="-20 100"/>
        <geom name="{side}_thigh" pos="0 0 -0.225" size="0.05 0.225"/>
        <body name="{side}_leg" pos="0 0 -0.7">
          <joint name="{side}_knee" pos="0 0 0.25" range="-150 0"/>
          <geom name="{side}_leg" size="0.04 0.25"/>
          <body name="{side}_foot" pos="0.06 0 -0.25">
            <joint name="{side}_ankle" pos="-0.06 0 0" range="-45 45"/>
            <geom name="{side}_foot" zaxis="1 0 0" size="0.05 0.1"/>
          </body>
        </body>
      </body>"""

_WALKER_GEARS = {"hip": 100, "knee": 50, "ankle": 20}


def walker_xml() -> str:
    """MJCF text of dm_control's planar walker (right leg first, as in dm_control)."""
    legs = "".join(_WALKER_LEG.format(side=s, y=y) for s, y in (("right", "-.05"), ("left", ".05")))
    motors = "\n".join(
        f'    <motor name="{s}_{j}" joint="{s}_{j}" gear="{g}"/>'
        for s in ("right", "left")
        for j, g in _WALKER_GEARS.items()
    )
    return WALKER_XML.replace("{legs}", legs).replace("{motors}", motors)


# (name, body pos, joint range, stiffness, damping, geom pos, geom euler, geom half-length, gear)
_CHEETAH_LIMBS = {
    "b": (
        ("thigh", "-.5 0 0", "-30 60", 240, 6, ".1 0 -.13", "0 -218 0", ".145", 120),
        ("shin", ".16 0 -.25", "-50 50", 180, 4.5, "-.14 0 -.07", "0 -116 0", ".15", 90),
        ("foot", "-.28 0 -.14", "-230 50", 120, 3, ".03 0 -.097", "0 -15 0", ".094", 60),
    ),
    "f": (
        ("thigh", ".5 0 0", "-57 .40", 180, 4.5, "-.07 0 -.12", "0 30 0", ".133", 90),
        ("shin", "-.14 0 -.24", "-70 50", 120, 3, ".065 0 -.09", "0 -34 0", ".106", 60),
        ("foot", ".13 0 -.18", "-28 28", 60, 1.5, ".045 0 -.07", "0 -34 0", ".07", 30),
    ),
}

CHEETAH_XML = f"""
<mujoco model="cheetah">
{_MATERIALS}
  <default>
    <default class="cheetah">
      <joint limited="true" damping=".01" armature=".1" stiffness="8" type="hinge" axis="0 1 0"/>
      <geom contype="1" conaffinity="1" condim="3" friction=".4 .1 .1" material="self"/>
    </default>
    <default class="free">
      <joint limited="false" damping="0" armature="0" stiffness="0"/>
    </default>
    <motor ctrllimited="true" ctrlrange="-1 1"/>
  </default>
  <statistic center="0 0 .7" extent="2"/>
  <option timestep="0.01"/>
  <worldbody>
    <geom name="ground" type="plane" conaffinity="1" pos="98 0 0" size="100 .8 .5" material="grid"/>
    <body name="torso" pos="0 0 .7" childclass="cheetah">
      <light name="light" pos="0 0 2" mode="trackcom"/>
      <camera name="side" pos="0 -3 0" quat="0.707 0.707 0 0" mode="trackcom"/>
      <joint name="rootx" type="slide" axis="1 0 0" class="free"/>
      <joint name="rootz" type="slide" axis="0 0 1" class="free"/>
      <joint name="rooty" type="hinge" axis="0 1 0" class="free"/>
      <geom name="torso" type="capsule" fromto="-.5 0 0 .5 0 0" size="0.046"/>
      <geom name="head" type="capsule" pos=".6 0 .1" euler="0 50 0" size="0.046 .15"/>
{{limbs}}
    </body>
  </worldbody>
  <sensor>
    <subtreelinvel name="torso_subtreelinvel" body="torso"/>
  </sensor>
  <actuator>
{{motors}}
  </actuator>
</mujoco>
"""


def _cheetah_limb(prefix: str) -> str:
    opened, closes = [], []
    for depth, (part, pos, rng, stiff, damp, gpos, euler, half, _) in enumerate(_CHEETAH_LIMBS[prefix]):
        pad = "  " * (3 + depth)
        name = prefix + part
        opened.append(
            f'{pad}<body name="{name}" pos="{pos}">\n'
            f'{pad}  <joint name="{name}" range="{rng}" stiffness="{stiff}" damping="{damp}"/>\n'
            f'{pad}  <geom name="{name}" type="capsule" pos="{gpos}" euler="{euler}" size="0.046 {half}"/>'
        )
        closes.append(f"{pad}</body>")
    return "\n".join(opened + closes[::-1])


def cheetah_xml() -> str:
    """MJCF text of dm_control's half-cheetah."""
    limbs = "\n".join(_cheetah_limb(p) for p in ("b", "f"))
    motors = "\n".join(
        f'    <motor name="{p}{limb[0]}" joint="{p}{limb[0]}" gear="{limb[-1]}"/>'
        for p in ("b", "f")
        for limb in _CHEETAH_LIMBS[p]
    )
    return CHEETAH_XML.replace("{limbs}", limbs).replace("{motors}", motors)


CHEETAH_TOTAL_MASS = 14.0
"""dm_control's cheetah sets ``<compiler settotalmass="14"/>``; we scale after compiling."""


def compile_model(xml: str, total_mass: float | None = None) -> mujoco.MjModel:
    """Compiles MJCF text with MuJoCo's own compiler.

    Args:
      xml: MJCF text.
      total_mass: if given, scales all masses and inertias so that they sum to it
        (what MJCF's deprecated ``settotalmass`` compiler attribute does).
    """
    model = mujoco.MjModel.from_xml_string(xml)
    if total_mass is not None:
        mujoco.mj_setTotalmass(model, total_mass)
        mujoco.mj_setConst(model, mujoco.MjData(model))
    return model
