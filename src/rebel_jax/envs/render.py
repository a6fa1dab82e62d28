"""A pure-JAX ray-cast camera that reproduces MuJoCo's OpenGL image of a model.

One primary ray per pixel (or ``supersample``**2 of them) is intersected with every visible
geom in plain ``jnp``; the hit is shaded the way MuJoCo's classic renderer shades it, with the
model's own camera, lights, materials, textures and skybox. Everything is read from the
compiled ``mujoco.MjModel`` once, on the host, into a :class:`Camera`; ``Camera.render`` is
then a pure function of ``mjx.Data`` (jittable, vmappable, differentiable nowhere that matters).

What MuJoCo's renderer does (``src/render/classic/render_gl3.c``, ``mjr_render``; MuJoCo
3.12), and what we do:

- Camera: ``trackcom`` / ``track`` / ``fixed`` cameras as ``mj_camlight``
  (``engine_core_smooth.c``); perspective with the camera's ``fovy``.
- Lights: the headlight (directional, along the camera's view, ``mjv_makeLights``) and the
  model's spot or directional lights, with OpenGL's fixed-function lighting equation (local
  viewer, one-sided, ``GL_COLOR_MATERIAL`` on ambient and diffuse, material specular and
  ``shininess * 128``). We shade per pixel with exact normals; MuJoCo shades per vertex of its
  tessellation, so highlights differ slightly.
- Shadows: MuJoCo renders each shadow-casting light in an extra additive pass through a
  shadow map whose frustum is ``2 * cutoff * shadowscale`` wide. We cast a shadow ray to the
  light inside that frustum (``shadows=True``), or leave the light unshadowed.
- Textures: a 2D texture on a plane (dm_control's checker floor) is sampled with the plane's
  texture coordinates (``render_context.c``, ``makePlane``; ``texrepeat``, ``texuniform``),
  from a box-filtered copy of the texture (``texture_size``), bilinearly with wrap-around.
- Skybox: drawn where no geom is hit, a cube map looked up along the view ray with the skybox
  mapping of ``settexture``. dm_control's skybox is a vertical gradient with 1% random white
  marks; we tabulate the cube map's mean colour by elevation (``sky_bins``), marks included.
- Reflection: the first reflective plane adds the reflected opaque geoms, lit by every light
  and with their colour scaled by the plane's ``reflectance``, as MuJoCo's stencil pass does;
  the sky is not reflected.
- Not reproduced: per-vertex (Gouraud) lighting, 4x multisampling of edges (use
  ``supersample``), transparency (alpha is ignored), haze, fog, textures on anything but
  planes.

Supported geom types: plane, sphere, capsule. Making a camera for a model with another
visible geom type raises ``ValueError``.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

SUPPORTED_GEOMS = {
    int(mujoco.mjtGeom.mjGEOM_PLANE): "plane",
    int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
}
_PLANE, _SPHERE, _CAPSULE = (int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_SPHERE),
                             int(mujoco.mjtGeom.mjGEOM_CAPSULE))  # fmt: skip
_VISIBLE_GROUPS = 3  # mjv_defaultOption shows geom groups 0, 1 and 2.
_EPS = 1e-4


class _Vec(NamedTuple):
    """A 3-vector as three arrays of one shape (or scalars), so that vector algebra stays elementwise.

    The camera's per-pixel arithmetic is written on components rather than on (..., 3) arrays:
    XLA then fuses a whole ray's intersection and shading into few loops over pixels, with no
    reduction over a size-3 axis and no (pixels, geoms, 3) intermediate going through memory.
    """

    x: jax.Array
    y: jax.Array
    z: jax.Array

    @staticmethod
    def of(a) -> _Vec:
        """Components of an array (..., 3)."""
        return _Vec(a[..., 0], a[..., 1], a[..., 2])

    def __add__(self, o: _Vec) -> _Vec:  # type: ignore[override]
        return _Vec(self.x + o.x, self.y + o.y, self.z + o.z)

    def __sub__(self, o: _Vec) -> _Vec:
        return _Vec(self.x - o.x, self.y - o.y, self.z - o.z)

    def __neg__(self) -> _Vec:
        return _Vec(-self.x, -self.y, -self.z)

    def __mul__(self, s) -> _Vec:  # type: ignore[override]
        """Times a scalar (array) ``s``, or componentwise times another :class:`_Vec`."""
        if isinstance(s, _Vec):
            return _Vec(self.x * s.x, self.y * s.y, self.z * s.z)
        return _Vec(self.x * s, self.y * s, self.z * s)

    def dot(self, o: _Vec) -> jax.Array:
        return self.x * o.x + self.y * o.y + self.z * o.z

    def normalized(self, floor: float) -> _Vec:
        return self * (1.0 / jnp.maximum(jnp.sqrt(self.dot(self)), floor))

    def map(self, f) -> _Vec:
        return _Vec(f(self.x), f(self.y), f(self.z))

    def stack(self) -> jax.Array:
        return jnp.stack(jnp.broadcast_arrays(self.x, self.y, self.z), -1)


def _where(cond: jax.Array, a: _Vec, b: _Vec) -> _Vec:
    return _Vec(jnp.where(cond, a.x, b.x), jnp.where(cond, a.y, b.y), jnp.where(cond, a.z, b.z))


def _pick(idx: jax.Array, values, cands) -> jax.Array | _Vec:
    """``values[idx]`` for ``idx`` among geoms ``cands``, as a chain of selects (no gather).

    ``values``: one entry (scalar, array or :class:`_Vec`) per rendered geom. Equal Python or
    NumPy constants over ``cands`` come back as that constant.
    """
    vals = [values[g] for g in cands]
    if not isinstance(vals[0], (_Vec, jax.Array)) and all(np.array_equal(v, vals[0]) for v in vals):
        return vals[0]
    out = vals[0]
    for g, v in zip(cands[1:], vals[1:], strict=True):
        out = _where(idx == g, v, out) if isinstance(v, _Vec) else jnp.where(idx == g, v, out)
    return out


class _Frame(NamedTuple):
    """A rendered geom's pose in one state: position and the columns of its rotation (local x, y, z)."""

    pos: _Vec
    ax: tuple[_Vec, _Vec, _Vec]

    def local(self, p: _Vec) -> _Vec:
        """World point ``p`` in the geom's frame."""
        d = p - self.pos
        return _Vec(d.dot(self.ax[0]), d.dot(self.ax[1]), d.dot(self.ax[2]))

    def rotate_in(self, v: _Vec) -> _Vec:
        """World direction ``v`` in the geom's frame."""
        return _Vec(v.dot(self.ax[0]), v.dot(self.ax[1]), v.dot(self.ax[2]))


def _hit_plane(o: _Vec, v: _Vec, size: np.ndarray) -> jax.Array:
    """Distance along the ray ``o + t v`` (plane frame) to the front of a plane (inf: none).

    A plane of size (x, y) > 0 is a rectangle, as MuJoCo renders it; it is seen from the front only.
    """
    front = v.z < -1e-9
    t = -o.z / jnp.where(front, v.z, -1.0)
    ok = front & (t > _EPS)
    for half, oc, vc in ((size[0], o.x, v.x), (size[1], o.y, v.y)):
        if half > 0:
            ok = ok & (jnp.abs(oc + t * vc) <= half)
    return jnp.where(ok, t, jnp.inf)


def _geom_type_name(t: int) -> str:
    return mujoco.mjtGeom(t).name.removeprefix("mjGEOM_").lower()


@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """A camera of a model, ready to render ``mjx.Data`` of that model. Build with :func:`make_camera`.

    Array attributes are NumPy constants of the model (per visible geom ``g`` and light ``l``).

    Attributes:
      height, width: image size in pixels.
      supersample: rays per pixel along each axis (averaged).
      shadows: cast shadow rays for shadow-casting lights.
      reflections: add the reflective plane's mirror image.
      geom_ids: model geom id of each rendered geom.
    """

    height: int
    width: int
    supersample: int
    shadows: bool
    reflections: bool
    # camera
    cam_mode: int
    cam_body: int
    cam_pos: np.ndarray  # poscom0 / pos0 / local pos, by mode
    cam_mat: np.ndarray  # mat0 / local mat, by mode
    ray_dirs: np.ndarray  # (P, 3) in the camera frame
    # geoms
    geom_ids: np.ndarray
    geom_type: np.ndarray
    geom_size: np.ndarray
    geom_rgb: np.ndarray
    geom_specular: np.ndarray
    geom_shininess: np.ndarray
    geom_emission: np.ndarray
    geom_tex: np.ndarray  # index into textures, -1 for none
    geom_texscale: np.ndarray  # (g, 2)
    reflective: int  # index (into the rendered geoms) of the reflective plane, -1 for none
    reflectance: float
    textures: np.ndarray  # (ntex, R, R, 3) float32
    # lights: headlight first
    light_mode: np.ndarray
    light_body: np.ndarray
    light_pos: np.ndarray
    light_dir: np.ndarray
    light_directional: np.ndarray
    light_shadow: np.ndarray
    light_ambient: np.ndarray
    light_diffuse: np.ndarray
    light_specular: np.ndarray
    light_attenuation: np.ndarray
    light_cos_cutoff: np.ndarray
    light_exponent: np.ndarray
    light_cos_shadow: np.ndarray
    global_ambient: float
    sky: np.ndarray  # (bins, 3) colour by elevation from -90 to 90 degrees

    def _frame(self, d) -> tuple[jax.Array, jax.Array]:
        """Camera position and camera-to-world rotation (columns: right, up, back)."""
        if self.cam_mode == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM):
            return d.subtree_com[self.cam_body] + self.cam_pos, jnp.asarray(self.cam_mat)
        if self.cam_mode == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACK):
            return d.xpos[self.cam_body] + self.cam_pos, jnp.asarray(self.cam_mat)
        xmat = d.xmat[self.cam_body]
        return d.xpos[self.cam_body] + xmat @ self.cam_pos, xmat @ self.cam_mat

    def _lights(self, d, eye, forward) -> list[tuple[_Vec, _Vec]]:
        """Each light's world position and unit direction (scalars of the state)."""
        lights = []
        for i in range(len(self.light_mode)):
            mode, body = int(self.light_mode[i]), int(self.light_body[i])
            if mode < 0:  # headlight
                pos, direction = eye, forward
            elif mode == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM):
                pos, direction = d.subtree_com[body] + self.light_pos[i], jnp.asarray(self.light_dir[i])
            elif mode == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACK):
                pos, direction = d.xpos[body] + self.light_pos[i], jnp.asarray(self.light_dir[i])
            else:
                pos, direction = d.xpos[body] + d.xmat[body] @ self.light_pos[i], d.xmat[body] @ self.light_dir[i]
            lights.append((_Vec.of(pos), _Vec.of(direction / jnp.linalg.norm(direction))))
        return lights

    def _geom_arrays(self, d) -> tuple[jax.Array, jax.Array]:
        ids = jnp.asarray(self.geom_ids)
        return d.geom_xpos[ids], d.geom_xmat[ids]

    def _geoms(self, d) -> list[_Frame]:
        gpos, gmat = self._geom_arrays(d)
        return [
            _Frame(_Vec.of(gpos[g]), tuple(_Vec.of(gmat[g][:, k]) for k in range(3))) for g in range(len(self.geom_ids))
        ]

    def _order(self, skip: int = -1) -> list[int]:
        """Rendered geoms a ray is tested against, planes first (ties go to the first)."""
        keep = np.arange(len(self.geom_type)) != skip
        planes = np.flatnonzero(keep & (self.geom_type == _PLANE))
        rounds = np.flatnonzero(keep & ((self.geom_type == _SPHERE) | (self.geom_type == _CAPSULE)))
        return [int(g) for g in np.concatenate([planes, rounds])]

    def _hit_rounds(self, gpos, gmat, ids: np.ndarray, origin: _Vec, dirs: _Vec) -> jax.Array:
        """Distances (..., G) along rays ``origin + t * dirs`` to the round geoms ``ids`` (inf: none).

        Vectorised over the geoms on a trailing axis, so that the nearest hit is one reduction whose
        input XLA fuses (the (pixels, G) distances need not go through memory). Terms of a shared
        origin (the camera's eye) are computed once per frame.
        """
        pos, mat = gpos[ids], gmat[ids]  # (G, 3), (G, 3, 3)
        rel = [c[..., None] - pos[:, j] for j, c in enumerate(origin)]
        d = [c[..., None] for c in dirs]
        o = _Vec(*(sum(rel[j] * mat[:, j, k] for j in range(3)) for k in range(3)))
        v = _Vec(*(sum(d[j] * mat[:, j, k] for j in range(3)) for k in range(3)))
        capsule = self.geom_type[ids] == _CAPSULE
        radius, half = self.geom_size[ids, 0], np.where(capsule, self.geom_size[ids, 1], 0.0).astype(np.float32)
        oxy2 = o.x * o.x + o.y * o.y
        bxy = o.x * v.x + o.y * v.y
        # Cylinder side: |o_xy + t v_xy| = r, between the end caps.
        a = v.x * v.x + v.y * v.y
        disc = bxy * bxy - a * (oxy2 - radius**2)
        # The entry at num / a, tested before the division so that the quotient has one use.
        num = -bxy - jnp.sqrt(jnp.maximum(disc, 0.0))
        ok = capsule & (a > 1e-12) & (disc > 0) & (num > _EPS * a) & (jnp.abs(o.z * a + num * v.z) <= half * a)
        t = jnp.where(ok, num / jnp.where(a > 1e-12, a, 1.0), jnp.inf)
        # End spheres: |o - (0, 0, s h) + t v| = r, on the outer half (s z >= h).
        for sign in (1.0, -1.0):
            oz = o.z - sign * half
            b = bxy + oz * v.z
            disc = b * b - (oxy2 + oz * oz - radius**2)
            cap = -b - jnp.sqrt(jnp.maximum(disc, 0.0))
            ok = (disc > 0) & (cap > _EPS) & (sign * (o.z + cap * v.z) >= half)
            t = jnp.minimum(t, jnp.where(ok, cap, jnp.inf))
        return t

    def _intersect(self, frames, gpos, gmat, origin: _Vec, dirs: _Vec, skip: int = -1, index: bool = True):
        """Nearest hit of rays ``origin + t * dirs``: (t, rendered geom index, or None if not ``index``).

        ``t`` is ``inf`` where nothing is hit. Geom ``skip`` (an index into the rendered geoms) is ignored.
        Planes one at a time, round geoms in one reduction; ties go to planes, then to the first geom.
        """
        keep = np.arange(len(self.geom_type)) != skip
        planes = np.flatnonzero(keep & (self.geom_type == _PLANE))
        rounds = np.flatnonzero(keep & ((self.geom_type == _SPHERE) | (self.geom_type == _CAPSULE)))
        shape = jnp.broadcast_shapes(*(jnp.shape(c) for c in (*origin, *dirs)))
        t = jnp.full(shape, jnp.inf)
        first = int(planes[0]) if planes.size else int(rounds[0]) if rounds.size else 0
        idx = jnp.full(shape, first, jnp.int32)
        for g in planes:
            frame = frames[g]
            tg = _hit_plane(frame.local(origin), frame.rotate_in(dirs), self.geom_size[g])
            closer = tg < t
            t = jnp.where(closer, tg, t)
            idx = jnp.where(closer, int(g), idx) if index else idx
        if rounds.size:
            tr = self._hit_rounds(gpos, gmat, rounds, origin, dirs)
            if index:
                ids = jnp.broadcast_to(jnp.asarray(rounds.astype(np.int32)), tr.shape)

                def nearer(x, y):
                    pick = (y[0] < x[0]) | ((y[0] == x[0]) & (y[1] < x[1]))
                    return jnp.where(pick, y[0], x[0]), jnp.where(pick, y[1], x[1])

                big = np.int32(np.iinfo(np.int32).max)
                tr, ir = jax.lax.reduce((tr, ids), (np.float32(np.inf), big), nearer, (tr.ndim - 1,))
                closer = tr < t
                idx = jnp.where(closer, ir, idx)
            else:
                tr = jnp.min(tr, axis=-1)
                closer = tr < t
            t = jnp.where(closer, tr, t)
        return t, idx if index else None

    def _normal(self, frames, idx, cands, points: _Vec) -> _Vec:
        """Unit world normal at ``points`` on geoms ``idx`` (among ``cands``)."""
        pos = _pick(idx, [f.pos for f in frames], cands)
        axis = _pick(idx, [f.ax[2] for f in frames], cands)
        half = _pick(idx, np.where(self.geom_type == _CAPSULE, self.geom_size[:, 1], 0.0).tolist(), cands)
        rel = points - pos
        # Round geoms: from the nearest point of the axis segment; planes: the local z axis.
        zc = jnp.clip(rel.dot(axis), -half, half)
        n = _where(_pick(idx, (self.geom_type == _PLANE).tolist(), cands), axis, rel - axis * zc)
        return n.normalized(1e-12)

    def _texture(self, frames, idx, points: _Vec) -> _Vec | float:
        """Texture colour at ``points`` of geoms ``idx`` (1 where untextured): each textured plane samples its own."""
        color = 1.0
        res = self.textures.shape[1]
        # One flat table per channel: (tex, row, col) -> value.
        tables = [jnp.asarray(self.textures[..., k].reshape(-1)) for k in range(3)]
        for g in np.flatnonzero(self.geom_tex >= 0):
            size, scale, frame = self.geom_size[g], self.geom_texscale[g], frames[g]
            rel = points - frame.pos
            lx, ly = rel.dot(frame.ax[0]), rel.dot(frame.ax[1])
            # makePlane's texture coordinates, then settexture's scaling.
            u = (lx + size[0]) / (2 * size[0]) * scale[0]
            v = (1 - (ly + size[1]) / (2 * size[1])) * scale[1]
            x, y = u * res - 0.5, v * res - 0.5
            x0, y0 = jnp.floor(x), jnp.floor(y)
            fx, fy = x - x0, y - y0
            x0, y0 = x0.astype(jnp.int32) % res, y0.astype(jnp.int32) % res
            x1, y1 = (x0 + 1) % res, (y0 + 1) % res
            base = int(self.geom_tex[g]) * res * res
            taps = [(y0, x0, (1 - fx) * (1 - fy)), (y0, x1, fx * (1 - fy)), (y1, x0, (1 - fx) * fy), (y1, x1, fx * fy)]
            c = _Vec(*(sum(tab[base + r * res + q] * w for r, q, w in taps) for tab in tables))
            color = _where(idx == g, c, color if isinstance(color, _Vec) else _Vec(1.0, 1.0, 1.0))
        return color

    def _light_term(self, i: int, light, points: _Vec, normals: _Vec, view: _Vec, rgb: _Vec, spec, shin):
        """Light ``i``'s fixed-function contribution before shadowing, and the distance to it."""
        lpos, ldir = light
        to_light = lpos - points
        dist = jnp.sqrt(to_light.dot(to_light))
        if self.light_directional[i]:
            L, factor = -ldir, 1.0
        else:
            L = to_light * (1.0 / jnp.maximum(dist, 1e-9))
            a0, a1, a2 = (float(a) for a in self.light_attenuation[i])
            cos_spot = -L.dot(ldir)
            spot = jnp.where(
                cos_spot >= self.light_cos_cutoff[i], jnp.maximum(cos_spot, 0.0) ** self.light_exponent[i], 0.0
            )
            factor = spot / (a0 + a1 * dist + a2 * dist * dist)
        ndotl = normals.dot(L)
        ndoth = jnp.maximum(normals.dot((L + view).normalized(1e-9)), 0.0)
        specular = jnp.where((ndotl > 0) & (ndoth > 0), ndoth**shin, 0.0)
        amb, dif, spc = (
            _Vec(*(float(c) for c in a[i])) for a in (self.light_ambient, self.light_diffuse, self.light_specular)
        )
        color = rgb * (amb + dif * jnp.maximum(ndotl, 0.0)) + spc * (specular * spec)
        return color * factor, dist

    def _shade(
        self,
        frames,
        gpos,
        gmat,
        lights,
        points: _Vec,
        dirs: _Vec,
        idx,
        cands,
        rgb_scale: float = 1.0,
        shadows: bool = False,
    ):
        """Colour of hits at ``points`` on geoms ``idx`` (among ``cands``) along ``dirs``, as MuJoCo's passes sum it.

        ``gpos`` and ``gmat`` are the rendered geoms' positions and rotations, for shadow rays.
        """
        normals = self._normal(frames, idx, cands, points)
        rgb = _pick(idx, [_Vec(*(float(c) * rgb_scale for c in x)) for x in self.geom_rgb], cands)
        spec = _pick(idx, self.geom_specular.tolist(), cands)
        shin = _pick(idx, self.geom_shininess.tolist(), cands)
        emission = _pick(idx, self.geom_emission.tolist(), cands)
        tex = self._texture(frames, idx, points)
        if not isinstance(tex, _Vec):
            tex = _Vec(tex, tex, tex)
        terms = [self._light_term(i, light, points, normals, -dirs, rgb, spec, shin) for i, light in enumerate(lights)]
        clip = lambda c: c.map(lambda x: jnp.clip(x, 0.0, 1.0))  # noqa: E731
        # Regular pass: lights without shadows; then one additive pass per shadow-casting light.
        cast = self.light_shadow if shadows else np.zeros_like(self.light_shadow)
        main = rgb * (emission + self.global_ambient)
        for i in np.flatnonzero(~cast):
            main = main + terms[i][0]
        main = clip(main) * tex
        for i in np.flatnonzero(cast):
            term, dist = terms[i]
            lpos, ldir = lights[i]
            if self.light_directional[i]:
                shadow_dirs, limit = -ldir, jnp.inf
            else:
                shadow_dirs, limit = (lpos - points) * (1.0 / dist), dist
            t, _ = self._intersect(frames, gpos, gmat, points + normals * 1e-3, shadow_dirs, index=False)
            in_map = -shadow_dirs.dot(ldir) >= self.light_cos_shadow[i]
            lit = (t >= limit) | ~in_map
            main = main + clip(term) * tex * jnp.where(lit, 1.0, 0.0)
        return main

    def _sky(self, dirs: _Vec) -> _Vec:
        el = jnp.arcsin(jnp.clip(dirs.z, -1.0, 1.0)) / (np.pi / 2)
        x = (el + 1) / 2 * (self.sky.shape[0] - 1)
        i0 = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, self.sky.shape[0] - 2)
        f = x - i0
        tabs = [jnp.asarray(self.sky[:, k]) for k in range(3)]
        return _Vec(*(tab[i0] * (1 - f) + tab[i0 + 1] * f for tab in tabs))

    def _rays(self, d, rays: np.ndarray | None = None) -> tuple[jax.Array, jax.Array, _Vec]:
        """Eye, camera rotation and unit world directions of the rays ``ray_dirs[rays]`` (all by default)."""
        eye, rot = self._frame(d)
        cam = self.ray_dirs if rays is None else self.ray_dirs[rays]
        if self.cam_mode == int(mujoco.mjtCamLight.mjCAMLIGHT_FIXED):
            dirs = jnp.asarray(cam) @ rot.T
            return eye, rot, _Vec.of(dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True))
        # A tracking camera keeps its rotation: the directions are constants of the camera.
        dirs = cam.astype(np.float64) @ self.cam_mat.astype(np.float64).T
        dirs = (dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)).astype(np.float32)
        return eye, rot, _Vec.of(jnp.asarray(dirs))

    def segment(self, d) -> tuple[jax.Array, jax.Array]:
        """Per-pixel model geom id (-1 for none) and distance along the ray, at pixel centres: (H, W) each."""
        frames = self._geoms(d)
        # Pixel centres only (the first ray of each pixel is at its centre when supersample is odd).
        eye, _, dirs = self._rays(d, self._centre_rays())
        t, idx = self._intersect(frames, *self._geom_arrays(d), _Vec.of(eye), dirs)
        gid = jnp.where(jnp.isfinite(t), jnp.asarray(self.geom_ids)[idx], -1)
        return gid.reshape(self.height, self.width), t.reshape(self.height, self.width)

    def _centre_rays(self) -> np.ndarray:
        s = self.supersample
        rows = np.arange(self.height)[:, None] * s + s // 2
        cols = np.arange(self.width)[None, :] * s + s // 2
        return (rows * self.width * s + cols).ravel()

    def render_float(self, d) -> jax.Array:
        """RGB in [0, 1], float32, (H, W, 3)."""
        frames, (gpos, gmat) = self._geoms(d), self._geom_arrays(d)
        eye, rot, dirs = self._rays(d)
        lights = self._lights(d, eye, -rot[:, 2])
        eye = _Vec.of(eye)
        t, idx = self._intersect(frames, gpos, gmat, eye, dirs)
        hit = jnp.isfinite(t)
        points = eye + dirs * jnp.where(hit, t, 0.0)
        everything = self._order()
        color = self._shade(frames, gpos, gmat, lights, points, dirs, idx, everything, shadows=self.shadows)
        if self.reflections and self.reflective >= 0:
            on_mirror = hit & (idx == self.reflective)
            n = frames[self.reflective].ax[2]
            rdirs = dirs - n * (2 * dirs.dot(n))
            rt, ridx = self._intersect(frames, gpos, gmat, points, rdirs, skip=self.reflective)
            rhit = on_mirror & jnp.isfinite(rt)
            rpoints = points + rdirs * jnp.where(rhit, rt, 0.0)
            others = self._order(self.reflective)
            if others:
                refl = self._shade(frames, gpos, gmat, lights, rpoints, rdirs, ridx, others, rgb_scale=self.reflectance)
                color = color + refl * jnp.where(rhit, 1.0, 0.0)
        color = _where(hit, color.map(lambda x: jnp.clip(x, 0.0, 1.0)), self._sky(dirs)).stack()
        s = self.supersample
        if s == 1:
            return color.reshape(self.height, self.width, 3)
        return color.reshape(self.height, s, self.width, s, 3).mean(axis=(1, 3))

    def render(self, d) -> jax.Array:
        """RGB frame of ``mjx.Data`` ``d``: uint8, (height, width, 3), row 0 at the top."""
        return jnp.round(self.render_float(d) * 255.0).astype(jnp.uint8)


def _box_filter(tex: np.ndarray, res: int) -> np.ndarray:
    """Area-average an (h, w, 3) texture to (res, res, 3) (a smaller texture is first repeated up)."""
    h, w = tex.shape[:2]
    tex = np.repeat(np.repeat(tex, -(-res // h), axis=0), -(-res // w), axis=1)
    h, w = tex.shape[:2]
    rows = np.minimum(np.arange(h) * res // h, res - 1)
    cols = np.minimum(np.arange(w) * res // w, res - 1)
    out = np.zeros((res, res, 3))
    np.add.at(out, (rows[:, None], cols[None, :]), tex)
    count = np.zeros((res, res))
    np.add.at(count, (rows[:, None], cols[None, :]), 1.0)
    return (out / count[..., None]).astype(np.float32)


def _sky_table(m: mujoco.MjModel, bins: int) -> np.ndarray:
    """Mean skybox colour by elevation, from the first skybox texture's cube map (black without one)."""
    skies = np.flatnonzero(m.tex_type == int(mujoco.mjtTexture.mjTEXTURE_SKYBOX))
    if skies.size == 0:
        return np.zeros((bins, 3), np.float32)
    i = int(skies[0])
    w, nc = int(m.tex_width[i]), int(m.tex_nchannel[i])
    data = m.tex_data[m.tex_adr[i] : m.tex_adr[i] + 6 * w * w * nc].reshape(6, w, w, nc)[..., :3] / 255.0
    # Texel centres on each face, in OpenGL's cube-map convention (major axis, sc, tc).
    sc = (np.arange(w) + 0.5) / w * 2 - 1
    s_, t_ = np.meshgrid(sc, sc)  # [row, col]: t from the row, s from the column
    one = np.ones_like(s_)
    faces = [  # direction (rx, ry, rz) for faces +X, -X, +Y, -Y, +Z, -Z
        (one, -t_, -s_), (-one, -t_, s_), (s_, one, t_), (s_, -one, -t_), (s_, -t_, one), (-s_, -t_, -one),
    ]  # fmt: skip
    # settexture's skybox mapping is (s, t, r) = (x, z, -y): the cube map's ry is the world's z.
    el = np.concatenate([np.arcsin(f[1] / np.sqrt(f[0] ** 2 + f[1] ** 2 + f[2] ** 2)).ravel() for f in faces])
    b = np.clip(((el / (np.pi / 2) + 1) / 2 * (bins - 1)).round().astype(int), 0, bins - 1)
    table = np.stack([np.bincount(b, data[..., k].ravel(), bins) for k in range(3)], -1)
    count = np.bincount(b, minlength=bins)[:, None]
    filled = count[:, 0] > 0
    for k in range(3):  # fill empty bins by interpolation
        table[:, k] = np.interp(np.arange(bins), np.flatnonzero(filled), table[filled, k] / count[filled, 0])
    return table.astype(np.float32)


def make_camera(
    m: mujoco.MjModel,
    camera: int | str = 0,
    height: int = 84,
    width: int = 84,
    shadows: bool = True,
    reflections: bool = True,
    supersample: int = 1,
    texture_size: int = 64,
    sky_bins: int = 256,
) -> Camera:
    """Builds a :class:`Camera` for ``m`` (a compiled ``mujoco.MjModel``) from the model's camera ``camera``.

    Args:
      m: the model (its geoms, materials, textures, lights, skybox and headlight are read).
      camera: camera id or name (dm_control's camera 0 is ``side`` in walker and cheetah).
      height, width: image size in pixels (>= 1).
      shadows: cast shadows from shadow-casting lights (MuJoCo's default).
      reflections: mirror the scene in the reflective plane (MuJoCo's default).
      supersample: rays per pixel along each axis, averaged (MuJoCo multisamples 4x).
      texture_size: side of the box-filtered copy of each plane texture that is sampled.
      sky_bins: elevation bins of the sky table.

    Raises:
      ValueError: an image size below 1, an unknown camera, or a visible geom of an
        unsupported type (the message names them).
    """
    if height < 1 or width < 1 or supersample < 1:
        raise ValueError(f"image size and supersample must be >= 1; got {height}x{width}, supersample {supersample}")
    cam = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, camera) if isinstance(camera, str) else int(camera)
    if not 0 <= cam < m.ncam:
        raise ValueError(f"camera {camera!r} not in the model (it has {m.ncam} cameras)")
    mode = int(m.cam_mode[cam])
    if mode == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM):
        cam_pos, cam_mat = m.cam_poscom0[cam], m.cam_mat0[cam].reshape(3, 3)
    elif mode == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACK):
        cam_pos, cam_mat = m.cam_pos0[cam], m.cam_mat0[cam].reshape(3, 3)
    elif mode == int(mujoco.mjtCamLight.mjCAMLIGHT_FIXED):
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, m.cam_quat[cam])
        cam_pos, cam_mat = m.cam_pos[cam], mat.reshape(3, 3)
    else:
        raise ValueError(f"camera {camera!r}: mode {mujoco.mjtCamLight(mode).name} is not supported")
    # Ray directions through sample points, in the camera frame (x right, y up, z back).
    tan = np.tan(np.deg2rad(m.cam_fovy[cam]) / 2)
    rows = (np.arange(height * supersample) + 0.5) / (height * supersample)
    cols = (np.arange(width * supersample) + 0.5) / (width * supersample)
    y, x = np.meshgrid((1 - 2 * rows) * tan, (2 * cols - 1) * tan * width / height, indexing="ij")
    ray_dirs = np.stack([x, y, -np.ones_like(x)], -1).reshape(-1, 3)

    # Visible geoms (mjv_defaultOption: groups 0-2; MuJoCo skips fully transparent geoms).
    ids, unsupported = [], []
    matid = m.geom_matid
    for g in range(m.ngeom):
        rgba = m.mat_rgba[matid[g]] if matid[g] >= 0 else m.geom_rgba[g]
        if m.geom_group[g] >= _VISIBLE_GROUPS or rgba[3] == 0:
            continue
        if int(m.geom_type[g]) not in SUPPORTED_GEOMS:
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or f"#{g}"
            unsupported.append(f"{name} ({_geom_type_name(int(m.geom_type[g]))})")
        ids.append(g)
    if unsupported:
        raise ValueError(
            f"rebel_jax.envs.render supports geom types {', '.join(SUPPORTED_GEOMS.values())}; "
            f"unsupported visible geoms: {', '.join(unsupported)}"
        )
    ids = np.array(ids, np.int32)
    # Colour: the material's unless the geom sets its own rgba (mjv_updateScene's rule).
    default_rgba = np.array([0.5, 0.5, 0.5, 1.0], np.float32)
    rgb, specular, shininess, emission, tex, texscale = [], [], [], [], [], []
    reflective, reflectance = -1, 0.0
    textures, tex_index = [], {}
    rgb_role = int(mujoco.mjtTextureRole.mjTEXROLE_RGB)
    for k, g in enumerate(ids):
        mat = int(matid[g])
        own = mat < 0 or not np.allclose(m.geom_rgba[g], default_rgba)
        rgb.append(m.geom_rgba[g][:3] if own else m.mat_rgba[mat][:3])
        specular.append(m.mat_specular[mat] if mat >= 0 else 0.5)
        shininess.append((m.mat_shininess[mat] if mat >= 0 else 0.5) * 128.0)
        emission.append(m.mat_emission[mat] if mat >= 0 else 0.0)
        texid = int(m.mat_texid[mat, rgb_role]) if mat >= 0 else -1
        scale = np.ones(2)
        if texid >= 0 and m.tex_type[texid] == int(mujoco.mjtTexture.mjTEXTURE_2D):
            if m.geom_type[g] != _PLANE:
                name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, int(g)) or f"#{g}"
                raise ValueError(f"geom {name}: 2D textures are supported on planes only")
            if texid not in tex_index:
                tw, th, nc = int(m.tex_width[texid]), int(m.tex_height[texid]), int(m.tex_nchannel[texid])
                data = m.tex_data[m.tex_adr[texid] : m.tex_adr[texid] + tw * th * nc].reshape(th, tw, nc)
                tex_index[texid] = len(textures)
                textures.append(_box_filter(data[..., :3] / 255.0, texture_size))
            repeat = m.mat_texrepeat[mat]
            scale = np.where(repeat > 0, repeat, 1.0)
            if m.mat_texuniform[mat]:
                scale = scale * np.where(m.geom_size[g, :2] > 0, m.geom_size[g, :2], 1.0)
            tex.append(tex_index[texid])
        else:
            tex.append(-1)
        texscale.append(scale)
        if reflective < 0 and mat >= 0 and m.mat_reflectance[mat] > 0 and m.geom_type[g] == _PLANE:
            reflective, reflectance = k, float(m.mat_reflectance[mat])

    # Lights: the headlight, then the model's active lights.
    modes, bodies, pos, dirs, directional, shadow = [], [], [], [], [], []
    ambient, diffuse, spec_l, atten, cutoff, expo = [], [], [], [], [], []
    if m.vis.headlight.active:
        modes.append(-1), bodies.append(0), pos.append(np.zeros(3)), dirs.append(np.array([0.0, 0.0, -1.0]))
        directional.append(True), shadow.append(False), atten.append([1.0, 0.0, 0.0])
        ambient.append(m.vis.headlight.ambient), diffuse.append(m.vis.headlight.diffuse)
        spec_l.append(m.vis.headlight.specular), cutoff.append(180.0), expo.append(0.0)
    for i in range(m.nlight):
        if not m.light_active[i]:
            continue
        ltype = int(m.light_type[i])
        if ltype not in (int(mujoco.mjtLightType.mjLIGHT_SPOT), int(mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)):
            continue  # MuJoCo's classic renderer ignores point and image lights too
        lmode = int(m.light_mode[i])
        if lmode == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM):
            pos.append(m.light_poscom0[i]), dirs.append(m.light_dir0[i])
        elif lmode == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACK):
            pos.append(m.light_pos0[i]), dirs.append(m.light_dir0[i])
        elif lmode == int(mujoco.mjtCamLight.mjCAMLIGHT_FIXED):
            pos.append(m.light_pos[i]), dirs.append(m.light_dir[i])
        else:
            raise ValueError(f"light {i}: mode {mujoco.mjtCamLight(lmode).name} is not supported")
        is_dir = ltype == int(mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
        modes.append(lmode), bodies.append(int(m.light_bodyid[i])), directional.append(is_dir)
        shadow.append(bool(m.light_castshadow[i])), ambient.append(m.light_ambient[i])
        diffuse.append(m.light_diffuse[i]), spec_l.append(m.light_specular[i])
        atten.append([1.0, 0.0, 0.0] if is_dir else m.light_attenuation[i])
        cutoff.append(180.0 if is_dir else m.light_cutoff[i]), expo.append(0.0 if is_dir else m.light_exponent[i])
    cutoff = np.asarray(cutoff, np.float64)
    cos_cutoff = np.where(cutoff >= 180.0, -2.0, np.cos(np.deg2rad(np.minimum(cutoff, 90.0))))
    # The shadow map's frustum (mjr_render): 2 * cutoff * shadowscale wide, at most 160 degrees.
    shadow_half = np.minimum(cutoff * m.vis.map.shadowscale, 80.0)
    cos_shadow = np.where(np.asarray(directional), -2.0, np.cos(np.deg2rad(shadow_half)))
    f32 = lambda x: np.asarray(x, np.float32)
    return Camera(
        height=height,
        width=width,
        supersample=supersample,
        shadows=shadows,
        reflections=reflections,
        cam_mode=mode,
        cam_body=int(m.cam_bodyid[cam]),
        cam_pos=f32(cam_pos),
        cam_mat=f32(cam_mat),
        ray_dirs=f32(ray_dirs),
        geom_ids=ids,
        geom_type=np.asarray(m.geom_type[ids], np.int32),
        geom_size=f32(m.geom_size[ids]),
        geom_rgb=f32(rgb),
        geom_specular=f32(specular),
        geom_shininess=f32(shininess),
        geom_emission=f32(emission),
        geom_tex=np.asarray(tex, np.int32),
        geom_texscale=f32(texscale),
        reflective=reflective,
        reflectance=reflectance,
        textures=f32(np.stack(textures)) if textures else np.zeros((0, 1, 1, 3), np.float32),
        light_mode=np.asarray(modes, np.int32),
        light_body=np.asarray(bodies, np.int32),
        light_pos=f32(pos).reshape(-1, 3),
        light_dir=f32(dirs).reshape(-1, 3),
        light_directional=np.asarray(directional, bool),
        light_shadow=np.asarray(shadow, bool),
        light_ambient=f32(ambient).reshape(-1, 3),
        light_diffuse=f32(diffuse).reshape(-1, 3),
        light_specular=f32(spec_l).reshape(-1, 3),
        light_attenuation=f32(atten).reshape(-1, 3),
        light_cos_cutoff=f32(cos_cutoff),
        light_exponent=f32(expo),
        light_cos_shadow=f32(cos_shadow),
        global_ambient=0.0 if modes else 0.3,
        sky=_sky_table(m, sky_bins),
    )
