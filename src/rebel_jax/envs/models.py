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


def compile_model(
    xml: str, total_mass: float | None = None, excludes: tuple[tuple[str, str], ...] = ()
) -> mujoco.MjModel:
    """Compiles MJCF text with MuJoCo's own compiler.

    Args:
      xml: MJCF text.
      total_mass: if given, scales all masses and inertias so that they sum to it
        (what MJCF's deprecated ``settotalmass`` compiler attribute does).
      excludes: body pairs whose geoms never collide (MJCF's ``<contact><exclude>``), added to the model.
    """
    spec = mujoco.MjSpec.from_string(xml)
    for body1, body2 in excludes:
        spec.add_exclude(bodyname1=body1, bodyname2=body2)
    model = spec.compile()
    if total_mass is not None:
        mujoco.mj_setTotalmass(model, total_mass)
        mujoco.mj_setConst(model, mujoco.MjData(model))
    return model


# The quadruped's legs in dm_control's order (front left, front right, back right, back left): name, hip position
# on the torso, hip yaw (degrees).
QUADRUPED_LEGS = (
    ("front_left", ".2 .2 0", 45),
    ("front_right", ".2 -.2 0", -45),
    ("back_right", "-.2 -.2 0", -135),
    ("back_left", "-.2 .2 0", 135),
)

_QUADRUPED_LEG = """
      <body name="hip_{leg}" pos="{pos}" euler="0 0 {yaw}" childclass="hip">
        <joint name="yaw_{leg}" class="yaw"/>
        <joint name="pitch_{leg}" class="pitch"/>
        <geom name="thigh_{leg}"/>
        <body name="knee_{leg}" pos=".3 0 .11" childclass="knee">
          <joint name="knee_{leg}"/>
          <geom name="shin_{leg}"/>
          <body name="ankle_{leg}" pos=".25 0 -.25" childclass="ankle">
            <joint name="ankle_{leg}"/>
            <geom name="foot_{leg}"/>
            <body name="toe_{leg}" pos="0 0 -.3" childclass="toe">
              <geom name="toe_{leg}"/>
              <site name="toe_{leg}"/>
            </body>
          </body>
        </body>
      </body>"""

# Per leg: a coupling tendon (pitch + knee + ankle, held at 0 by an equality constraint), and the tendons that the
# lift and extend actuators pull.
_QUADRUPED_TENDONS = """
    <fixed name="extend_{leg}">
      <joint joint="pitch_{leg}" coef=".25"/>
      <joint joint="knee_{leg}" coef="-.5"/>
      <joint joint="ankle_{leg}" coef=".25"/>
    </fixed>
    <fixed name="lift_{leg}">
      <joint joint="pitch_{leg}" coef=".5"/>
      <joint joint="ankle_{leg}" coef="-.5"/>
    </fixed>"""

_QUADRUPED_COUPLING = """
    <fixed name="coupling_{leg}">
      <joint joint="pitch_{leg}" coef=".333"/>
      <joint joint="knee_{leg}" coef=".333"/>
      <joint joint="ankle_{leg}" coef=".333"/>
    </fixed>"""

QUADRUPED_XML = f"""
<mujoco model="quadruped">
{_MATERIALS}
  <visual>
    <map znear=".005" zfar="20"/>
  </visual>
  <asset>
    <material name="effector" rgba=".7 .4 .2 1"/>
    <material name="eye" rgba="0 .2 1 1"/>
    <material name="site" rgba=".5 .5 .5 .3"/>
  </asset>
  <option timestep=".005"/>
  <default>
    <geom solimp=".9 .99 .003" solref=".01 1"/>
    <default class="body">
      <geom type="capsule" size=".08" condim="1" material="self" density="500"/>
      <joint type="hinge" damping="30" armature=".01" limited="true" solimplimit="0 .99 .01"/>
      <default class="hip">
        <default class="yaw">
          <joint axis="0 0 1" range="-50 50"/>
        </default>
        <default class="pitch">
          <joint axis="0 1 0" range="-20 60"/>
        </default>
        <geom fromto="0 0 0 .3 0 .11"/>
      </default>
      <default class="knee">
        <joint axis="0 1 0" range="-60 50"/>
        <geom size=".065" fromto="0 0 0 .25 0 -.25"/>
      </default>
      <default class="ankle">
        <joint axis="0 1 0" range="-45 55"/>
        <geom size=".055" fromto="0 0 0 0 0 -.25"/>
      </default>
      <default class="toe">
        <geom type="sphere" size=".08" material="effector" friction="1.5"/>
        <site type="sphere" size=".084" material="site" group="4"/>
      </default>
    </default>
    <default class="rangefinder">
      <site type="capsule" size=".005 .1" material="site" group="4"/>
    </default>
    <default class="coupling">
      <equality solimp="0.95 0.99 0.01" solref=".005 .5"/>
    </default>
    <general ctrllimited="true" gainprm="1000" biasprm="0 -1000" biastype="affine" dyntype="filter" dynprm=".1"/>
    <default class="yaw_act">
      <general ctrlrange="-1 1"/>
    </default>
    <default class="lift_act">
      <general ctrlrange="-1 1.1"/>
    </default>
    <default class="extend_act">
      <general ctrlrange="-.8 .8"/>
    </default>
  </default>
  <worldbody>
    <geom name="floor" type="plane" size="{{floor}} {{floor}} .5" material="grid"/>
    <camera name="global" pos="-10 10 10" xyaxes="-1 -1 0 1 0 1" mode="trackcom"/>
    <body name="torso" childclass="body" pos="0 0 .57">
      <freejoint name="root"/>
      <camera name="x" pos="-1.7 0 1" xyaxes="0 -1 0 .75 0 1" mode="trackcom"/>
      <camera name="y" pos="0 4 2" xyaxes="-1 0 0 0 -.5 1" mode="trackcom"/>
      <camera name="egocentric" pos=".3 0 .11" xyaxes="0 -1 0 .4 0 1" fovy="60"/>
      <light name="light" pos="0 0 4" mode="trackcom"/>
      <geom name="eye_r" type="cylinder" size=".05" fromto=".1 -.07 .12 .31 -.07 .08" mass="0"/>
      <site name="pupil_r" type="sphere" size=".033" pos=".3 -.07 .08" zaxis="1 0 0" material="eye"/>
      <geom name="eye_l" type="cylinder" size=".05" fromto=".1 .07 .12 .31 .07 .08" mass="0"/>
      <site name="pupil_l" type="sphere" size=".033" pos=".3 .07 .08" zaxis="1 0 0" material="eye"/>
      <site name="workspace" type="sphere" size=".3 .3 .3" material="site" pos=".8 0 -.2" group="3"/>
{{rangefinders}}
      <geom name="torso" type="ellipsoid" size=".3 .27 .2" density="1000"/>
      <site name="torso_touch" type="box" size=".26 .26 .26" rgba="0 0 1 0"/>
      <site name="torso" size=".05" rgba="1 0 0 1"/>
{{legs}}
    </body>
  </worldbody>
  <tendon>
{{tendons}}
  </tendon>
  <equality>
{{couplings}}
  </equality>
  <actuator>
{{actuators}}
  </actuator>
  <sensor>
    <accelerometer name="imu_accel" site="torso"/>
    <gyro name="imu_gyro" site="torso"/>
    <velocimeter name="velocimeter" site="torso"/>
{{toe_sensors}}
    <subtreecom name="center_of_mass" body="torso"/>
  </sensor>
</mujoco>
"""


def _rangefinder_sites() -> str:
    """dm_control's 20 rangefinder sites on the head (``rf_<row><column>``): kept so that every site has
    dm_control's index, though the walk and run tasks remove the rangefinder sensors that read them."""
    sites = []
    for row in range(4):
        for col in range(5):
            y = -0.02 if (row, col) == (1, 1) else (col - 2) / 100  # rf_11 repeats rf_10's y in dm_control
            fromto = f".41 {y:g} {0.11 - row / 100:g} {0.34 + row / 50:g} 0 {0.115 - row / 200:g}"
            sites.append(f'      <site name="rf_{row}{col}" class="rangefinder" fromto="{fromto}"/>')
    return "\n".join(sites)


def quadruped_xml(floor_size: float) -> str:
    """MJCF text of dm_control's quadruped as ``quadruped.make_model(floor_size)`` builds it for the walk
    and run tasks: without the walls, ball, target, terrain and rangefinder sensors.

    Args:
      floor_size: the floor plane's half side in metres (dm_control: the time limit times the task's
        desired speed, 10 for walk and 100 for run).
    """
    legs = [leg for leg, _, _ in QUADRUPED_LEGS]
    act = ("yaw", "joint", "yaw_{leg}"), ("lift", "tendon", "lift_{leg}"), ("extend", "tendon", "extend_{leg}")
    actuators = "\n".join(
        f'    <general name="{kind}_{leg}" class="{kind}_act" {target}="{name.format(leg=leg)}"/>'
        for leg in legs
        for kind, target, name in act
    )
    toe_sensors = "\n".join(
        f'    <{kind} name="{kind}_toe_{leg}" site="toe_{leg}"/>' for kind in ("force", "torque") for leg in legs
    )
    parts = {
        "floor": f"{floor_size:g}",
        "rangefinders": _rangefinder_sites(),
        "legs": "".join(_QUADRUPED_LEG.format(leg=leg, pos=pos, yaw=yaw) for leg, pos, yaw in QUADRUPED_LEGS),
        "tendons": "".join(_QUADRUPED_COUPLING.format(leg=leg) for leg in legs)
        + "".join(_QUADRUPED_TENDONS.format(leg=leg) for leg in legs),
        "couplings": "\n".join(
            f'    <tendon name="coupling_{leg}" tendon1="coupling_{leg}" class="coupling"/>' for leg in legs
        ),
        "actuators": actuators,
        "toe_sensors": toe_sensors,
    }
    xml = QUADRUPED_XML
    for key, text in parts.items():
        xml = xml.replace("{" + key + "}", text)
    return xml
