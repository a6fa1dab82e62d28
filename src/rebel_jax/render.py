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


def _row_times(vec: jax.Array, mat: jax.Array) -> jax.Array:
    """``vec[..., k] @ mat[..., k, :]`` (vector times matrix, broadcasting), as elementwise products.

    Written out so that XLA fuses it into the intersection arithmetic instead of emitting a
    batched matrix product whose (pixels, geoms, 3) result goes through memory.
    """
    return vec[..., 0:1] * mat[..., 0, :] + vec[..., 1:2] * mat[..., 1, :] + vec[..., 2:3] * mat[..., 2, :]


def _hit_planes(o: jax.Array, v: jax.Array, size: np.ndarray, gtype: np.ndarray) -> jax.Array:
    """Distance along rays ``o + t v`` (local frames, (P, G, 3)) to the front of planes (inf: none).

    A plane of size (x, y) > 0 is a rectangle, as MuJoCo renders it; it is seen from the front only.
    """
    del gtype  # Unused.
    front = v[..., 2] < -1e-9
    t = -o[..., 2] / jnp.where(front, v[..., 2], -1.0)
    p = o[..., :2] + t[..., None] * v[..., :2]
    inside = np.all(size[:, :2] <= 0, axis=-1) | jnp.all((size[:, :2] <= 0) | (jnp.abs(p) <= size[:, :2]), axis=-1)
    return jnp.where(front & (t > _EPS) & inside, t, jnp.inf)


def _hit_rounds(o: jax.Array, v: jax.Array, size: np.ndarray, gtype: np.ndarray) -> jax.Array:
    """Distance along rays ``o + t v`` (local frames, (P, G, 3)) to spheres and capsules (inf: none).

    The entry point of a convex capsule is the nearest of its cylinder side and its two outer
    half-spheres (a sphere is a capsule of half-length 0). Rays that start inside miss.
    """
    r = size[:, 0]
    capsule = gtype == _CAPSULE
    half = np.where(capsule, size[:, 1], 0.0)
    # Cylinder side: |o_xy + t v_xy| = r, between the end caps.
    a = jnp.sum(v[..., :2] ** 2, -1)
    b = jnp.sum(o[..., :2] * v[..., :2], -1)
    c = jnp.sum(o[..., :2] ** 2, -1) - r**2
    disc = b * b - a * c
    side = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.where(a > 1e-12, a, 1.0)
    ok = capsule & (a > 1e-12) & (disc > 0) & (side > _EPS) & (jnp.abs(o[..., 2] + side * v[..., 2]) <= half)
    t = jnp.where(ok, side, jnp.inf)
    # End spheres: |o - (0, 0, s h) + t v| = r, on the outer half (s z >= h).
    for sign in (1.0, -1.0):
        oz = o[..., 2] - sign * half
        b = jnp.sum(o[..., :2] * v[..., :2], -1) + oz * v[..., 2]
        disc = b * b - (jnp.sum(o[..., :2] ** 2, -1) + oz**2 - r**2)
        cap = -b - jnp.sqrt(jnp.maximum(disc, 0.0))
        ok = (disc > 0) & (cap > _EPS) & (sign * (o[..., 2] + cap * v[..., 2]) >= half)
        t = jnp.minimum(t, jnp.where(ok, cap, jnp.inf))
    return t


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

    def _lights(self, d, eye, forward):
        pos, direction = [], []
        for i in range(len(self.light_mode)):
            mode, body = int(self.light_mode[i]), int(self.light_body[i])
            if mode < 0:  # headlight
                pos.append(eye), direction.append(forward)
            elif mode == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM):
                pos.append(d.subtree_com[body] + self.light_pos[i]), direction.append(jnp.asarray(self.light_dir[i]))
            elif mode == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACK):
                pos.append(d.xpos[body] + self.light_pos[i]), direction.append(jnp.asarray(self.light_dir[i]))
            else:
                pos.append(d.xpos[body] + d.xmat[body] @ self.light_pos[i])
                direction.append(d.xmat[body] @ self.light_dir[i])
        direction = jnp.stack(direction)
        return jnp.stack(pos), direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)

    def _intersect(self, gpos, gmat, origin, dirs, skip: int = -1):
        """Nearest hit of rays ``origin`` (P, 3) or (3,) + t * ``dirs`` (P, 3): (t, rendered geom index).

        ``t`` is ``inf`` where nothing is hit. Geom ``skip`` (an index into the rendered geoms) is ignored.
        """
        origin = jnp.broadcast_to(origin, dirs.shape)
        keep = np.arange(len(self.geom_type)) != skip
        planes = np.flatnonzero(keep & (self.geom_type == _PLANE))
        rounds = np.flatnonzero(keep & ((self.geom_type == _SPHERE) | (self.geom_type == _CAPSULE)))
        ts = []
        for ids, hit in ((planes, _hit_planes), (rounds, _hit_rounds)):
            if ids.size:
                # Rays in each geom's frame: (P, G, 3).
                o = _row_times(origin[:, None, :] - gpos[ids][None], gmat[ids][None])
                v = _row_times(dirs[:, None, :], gmat[ids][None])
                ts.append(hit(o, v, self.geom_size[ids], self.geom_type[ids]))
        if not ts:
            return jnp.full(dirs.shape[:1], jnp.inf), jnp.zeros(dirs.shape[:1], jnp.int32)
        t = jnp.concatenate(ts, axis=-1)
        k = jnp.argmin(t, axis=-1)
        order = jnp.asarray(np.concatenate([planes, rounds]).astype(np.int32))
        return jnp.take_along_axis(t, k[:, None], -1)[:, 0], order[k]

    def _normal_and_local(self, gpos, gmat, idx, points):
        """World normal at ``points`` on geoms ``idx``, and the points in the geoms' frames."""
        local = _row_times(points - gpos[idx], gmat[idx])
        half = jnp.asarray(np.where(self.geom_type == _CAPSULE, self.geom_size[:, 1], 0.0))[idx]
        axis_z = jnp.clip(local[:, 2], -half, half)
        round_n = local - jnp.stack([jnp.zeros_like(axis_z), jnp.zeros_like(axis_z), axis_z], -1)
        is_plane = jnp.asarray(self.geom_type == _PLANE)[idx]
        n_local = jnp.where(is_plane[:, None], jnp.array([0.0, 0.0, 1.0]), round_n)
        n = _row_times(n_local, jnp.swapaxes(gmat[idx], -1, -2))
        return n / jnp.maximum(jnp.linalg.norm(n, axis=-1, keepdims=True), 1e-12), local

    def _texture(self, idx, local):
        """Texture colour (P, 3) at plane-local points ``local`` of geoms ``idx`` (white if untextured)."""
        if self.textures.shape[0] == 0:
            return jnp.ones_like(local)
        tex = jnp.asarray(self.geom_tex)[idx]
        size = jnp.asarray(self.geom_size)[idx]
        scale = jnp.asarray(self.geom_texscale)[idx]
        # makePlane's texture coordinates, then settexture's scaling.
        u = (local[:, 0] + size[:, 0]) / (2 * size[:, 0]) * scale[:, 0]
        v = (1 - (local[:, 1] + size[:, 1]) / (2 * size[:, 1])) * scale[:, 1]
        res = self.textures.shape[1]
        x, y = u * res - 0.5, v * res - 0.5
        x0, y0 = jnp.floor(x), jnp.floor(y)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        x0, y0 = x0.astype(jnp.int32) % res, y0.astype(jnp.int32) % res
        x1, y1 = (x0 + 1) % res, (y0 + 1) % res
        texs = jnp.asarray(self.textures)
        t = jnp.maximum(tex, 0)
        c = (texs[t, y0, x0] * (1 - fx) * (1 - fy) + texs[t, y0, x1] * fx * (1 - fy)
             + texs[t, y1, x0] * (1 - fx) * fy + texs[t, y1, x1] * fx * fy)  # fmt: skip
        return jnp.where((tex >= 0)[:, None], c, 1.0)

    def _light_terms(self, lpos, ldir, points, normals, view, rgb, idx):
        """Each light's fixed-function contribution, (L, P, 3), before shadowing."""
        spec = jnp.asarray(self.geom_specular)[idx][None, :, None]
        shin = jnp.asarray(self.geom_shininess)[idx][None, :]
        directional = jnp.asarray(self.light_directional)[:, None]
        to_light = lpos[:, None, :] - points[None]
        dist = jnp.linalg.norm(to_light, axis=-1)
        L = jnp.where(directional[..., None], -ldir[:, None, :], to_light / jnp.maximum(dist, 1e-9)[..., None])
        att_c = jnp.asarray(self.light_attenuation)
        att = 1.0 / (att_c[:, 0:1] + att_c[:, 1:2] * dist + att_c[:, 2:3] * dist**2)
        cos_spot = jnp.sum(-L * ldir[:, None, :], -1)
        spot = jnp.where(
            cos_spot >= jnp.asarray(self.light_cos_cutoff)[:, None],
            jnp.maximum(cos_spot, 0.0) ** jnp.asarray(self.light_exponent)[:, None],
            0.0,
        )
        factor = jnp.where(directional, 1.0, att * spot)
        ndotl = jnp.sum(normals[None] * L, -1)
        H = L + view[None]
        H = H / jnp.maximum(jnp.linalg.norm(H, axis=-1, keepdims=True), 1e-9)
        ndoth = jnp.maximum(jnp.sum(normals[None] * H, -1), 0.0)
        specular = jnp.where(ndotl > 0, jnp.where(ndoth > 0, ndoth**shin, 0.0), 0.0)
        amb = jnp.asarray(self.light_ambient)[:, None, :]
        dif = jnp.asarray(self.light_diffuse)[:, None, :]
        spc = jnp.asarray(self.light_specular)[:, None, :]
        color = (
            amb * rgb[None] + jnp.maximum(ndotl, 0.0)[..., None] * dif * rgb[None] + specular[..., None] * spc * spec
        )
        return factor[..., None] * color, dist

    def _shade(self, gpos, gmat, lpos, ldir, points, dirs, idx, rgb_scale: float = 1.0, shadows: bool = False):
        """Colour of hits at ``points`` on geoms ``idx`` seen along ``dirs``, as MuJoCo's passes sum it."""
        normals, local = self._normal_and_local(gpos, gmat, idx, points)
        rgb = jnp.asarray(self.geom_rgb)[idx] * rgb_scale
        terms, dist = self._light_terms(lpos, ldir, points, normals, -dirs, rgb, idx)
        emission = jnp.asarray(self.geom_emission)[idx][:, None] * rgb + self.global_ambient * rgb
        tex = self._texture(idx, local)
        cast = jnp.asarray(self.light_shadow)
        if not shadows:
            return jnp.clip(emission + terms.sum(0), 0.0, 1.0) * tex
        # Regular pass: lights without shadows; then one additive pass per shadow-casting light.
        main = jnp.clip(emission + jnp.where(cast[:, None, None], 0.0, terms).sum(0), 0.0, 1.0) * tex
        for i in np.flatnonzero(self.light_shadow):
            to_light = lpos[i][None] - points
            if self.light_directional[i]:
                shadow_dirs, limit = -jnp.broadcast_to(ldir[i], points.shape), jnp.inf
            else:
                shadow_dirs, limit = to_light / dist[i][:, None], dist[i]
            t, _ = self._intersect(gpos, gmat, points + 1e-3 * normals, shadow_dirs)
            in_map = jnp.sum(-shadow_dirs * ldir[i], -1) >= self.light_cos_shadow[i]
            lit = (t >= limit) | ~in_map
            main = main + jnp.clip(terms[i], 0.0, 1.0) * tex * lit[:, None]
        return main

    def _sky(self, dirs):
        el = jnp.arcsin(jnp.clip(dirs[:, 2], -1.0, 1.0)) / (np.pi / 2)
        x = (el + 1) / 2 * (self.sky.shape[0] - 1)
        i0 = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, self.sky.shape[0] - 2)
        f = (x - i0)[:, None]
        sky = jnp.asarray(self.sky)
        return sky[i0] * (1 - f) + sky[i0 + 1] * f

    def _geoms(self, d):
        ids = jnp.asarray(self.geom_ids)
        return d.geom_xpos[ids], d.geom_xmat[ids]

    def _rays(self, d):
        eye, rot = self._frame(d)
        dirs = jnp.asarray(self.ray_dirs) @ rot.T
        return eye, rot, dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)

    def segment(self, d) -> tuple[jax.Array, jax.Array]:
        """Per-pixel model geom id (-1 for none) and distance along the ray, at pixel centres: (H, W) each."""
        gpos, gmat = self._geoms(d)
        eye, _, dirs = self._rays(d)
        # Pixel centres only (the first ray of each pixel is at its centre when supersample is odd).
        t, idx = self._intersect(gpos, gmat, eye, dirs[self._centre_rays()])
        gid = jnp.where(jnp.isfinite(t), jnp.asarray(self.geom_ids)[idx], -1)
        return gid.reshape(self.height, self.width), t.reshape(self.height, self.width)

    def _centre_rays(self) -> np.ndarray:
        s = self.supersample
        rows = np.arange(self.height)[:, None] * s + s // 2
        cols = np.arange(self.width)[None, :] * s + s // 2
        return (rows * self.width * s + cols).ravel()

    def render_float(self, d) -> jax.Array:
        """RGB in [0, 1], float32, (H, W, 3)."""
        gpos, gmat = self._geoms(d)
        eye, rot, dirs = self._rays(d)
        lpos, ldir = self._lights(d, eye, -rot[:, 2])
        t, idx = self._intersect(gpos, gmat, eye, dirs)
        hit = jnp.isfinite(t)
        points = eye + jnp.where(hit, t, 0.0)[:, None] * dirs
        color = self._shade(gpos, gmat, lpos, ldir, points, dirs, idx, shadows=self.shadows)
        if self.reflections and self.reflective >= 0:
            on_mirror = hit & (idx == self.reflective)
            n = gmat[self.reflective][:, 2]
            rdirs = dirs - 2 * jnp.sum(dirs * n, -1, keepdims=True) * n
            rt, ridx = self._intersect(gpos, gmat, points, rdirs, skip=self.reflective)
            rhit = on_mirror & jnp.isfinite(rt)
            rpoints = points + jnp.where(rhit, rt, 0.0)[:, None] * rdirs
            refl = self._shade(gpos, gmat, lpos, ldir, rpoints, rdirs, ridx, rgb_scale=self.reflectance)
            color = color + jnp.where(rhit[:, None], refl, 0.0)
        color = jnp.where(hit[:, None], jnp.clip(color, 0.0, 1.0), self._sky(dirs))
        s = self.supersample
        color = color.reshape(self.height, s, self.width, s, 3).mean(axis=(1, 3))
        return color

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
            f"rebel_jax.render supports geom types {', '.join(SUPPORTED_GEOMS.values())}; "
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
