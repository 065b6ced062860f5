"""Everything that touches Mitsuba 3: variant choice, scene construction, rays, G-buffers, radiance.

Variant: `llvm_ad_rgb` is ~2.4x faster but needs libLLVM 19 (LLVM 15/16 load and then *abort the
process* on the first render), so it is probed by a tiny render in a subprocess; `scalar_rgb` is the
fallback. The vectorised code paths below run on whole ray batches in llvm and loop per ray in scalar.

Ground truth is exact at pixel centres: one ray per pixel centre (the camera convention of docs/design.md, section 3) is
intersected with the scene and the BSDF's parameters are evaluated at the hit, so no anti-aliasing
blends depth, normals or materials across edges.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile

import numpy as np
import torch

from pipeline.data.synth.scene import Camera, Room
from pipeline.ops.camera import focal, pixel_directions

DEFAULT_LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
VARIANTS = ("llvm_ad_rgb", "scalar_rgb")

_PROBE = """
import mitsuba as mi
mi.set_variant('llvm_ad_rgb')
s = mi.load_dict({'type': 'scene', 'integrator': {'type': 'path'},
    'e': {'type': 'constant'}, 'r': {'type': 'rectangle'},
    'c': {'type': 'perspective', 'film': {'type': 'hdrfilm', 'width': 4, 'height': 4}}})
mi.render(s, spp=2)
print('ok')
"""


def _env_with_llvm() -> dict:
    env = dict(os.environ)
    if "DRJIT_LIBLLVM_PATH" not in env and os.path.exists(DEFAULT_LLVM):
        env["DRJIT_LIBLLVM_PATH"] = DEFAULT_LLVM
    return env


def choose_variant(requested: str = "auto") -> str:
    """Return the Mitsuba variant to use. `auto` probes llvm_ad_rgb in a subprocess (a failing LLVM
    aborts rather than raising) and falls back to scalar_rgb, printing why (the probe's exit status and
    the end of its stderr, or the timeout) to stderr."""
    if requested not in ("auto", *VARIANTS):
        raise ValueError(f"synth.variant={requested!r}: choose auto, llvm_ad_rgb or scalar_rgb")
    if requested != "auto":
        return requested
    try:
        out = subprocess.run(
            [sys.executable, "-c", _PROBE], env=_env_with_llvm(), capture_output=True, text=True, timeout=120
        )
    except subprocess.TimeoutExpired:
        why = "the llvm_ad_rgb probe render did not finish in 120 s"
    else:
        if out.returncode == 0 and "ok" in out.stdout:
            return "llvm_ad_rgb"
        tail = (out.stderr or "").strip().splitlines()[-3:]
        why = f"the llvm_ad_rgb probe exited with status {out.returncode}: {' | '.join(tail) or 'no stderr'}"
    print(
        f"synthesize: falling back to Mitsuba's scalar_rgb variant (about 2.4x slower): {why}. "
        "llvm_ad_rgb needs libLLVM 19 (apt-get install libllvm19; DRJIT_LIBLLVM_PATH).",
        file=sys.stderr,
    )
    return "scalar_rgb"


def init_mitsuba(variant: str, threads: int | None = None):
    """Set the process-wide variant (must precede building any Mitsuba object) and the thread count."""
    os.environ.update({k: v for k, v in _env_with_llvm().items() if k == "DRJIT_LIBLLVM_PATH"})
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(variant)
    if threads:
        dr.set_thread_count(int(threads))
    return mi


def _is_vectorised() -> bool:
    import mitsuba as mi

    return not mi.variant().startswith("scalar")


# ----------------------------------------------------------------------------------------------------
# Cameras (docs/design.md, section 3: OpenGL view space, pixel centres at +0.5)


def world_from_view(camera: Camera) -> np.ndarray:
    """(4, 4) matrix whose columns are the camera's right, up, back (= -forward) axes and its origin."""
    o, t = np.asarray(camera.origin, float), np.asarray(camera.target, float)
    fwd = (t - o) / np.linalg.norm(t - o)
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, -fwd, o
    return m


def intrinsics(fov_x_deg: float, width: int, height: int) -> dict[str, float]:
    """Pinhole intrinsics from the horizontal FOV: fx = fy = (W/2)/tan(fov_x/2), principal point at the centre."""
    f = float(focal(fov_x_deg, width))
    return {"fx": f, "fy": f, "cx": width / 2, "cy": height / 2}


def view_rays(fov_x_deg: float, width: int, height: int) -> np.ndarray:
    """(H*W, 3) unit view-space directions through pixel centres, row-major (row 0 = top)."""
    d = pixel_directions(height, width, fov_x_deg, dtype=torch.float64).reshape(-1, 3)
    return torch.nn.functional.normalize(d, dim=-1).numpy()


# ----------------------------------------------------------------------------------------------------
# Scene


def _sky_bitmap(sky, height: int = 128) -> np.ndarray:
    """Equirectangular sky in Mitsuba's envmap parametrisation: u = atan2(x, -z)/2pi, v = acos(y)/pi."""
    w = 2 * height
    v, u = np.meshgrid((np.arange(height) + 0.5) / height, (np.arange(w) + 0.5) / w, indexing="ij")
    theta, phi = v * math.pi, u * 2 * math.pi
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
    y = d[..., 1:2]
    zen, hor, gnd = (np.asarray(c, float) for c in (sky.zenith, sky.horizon, sky.ground))
    up_t = np.sqrt(np.clip(y, 0, 1))
    img = np.where(y >= 0, (1 - up_t) * hor + up_t * zen, gnd)
    ang = np.degrees(np.arccos(np.clip(d @ np.asarray(sky.sun_direction), -1, 1)))
    disc = np.clip((sky.sun_radius_deg - ang) / 0.75 + 0.5, 0, 1)[..., None]  # soft edge, fewer fireflies
    img = img + disc * np.asarray(sky.sun_radiance)
    return np.ascontiguousarray(img, dtype=np.float32)


def _texture_dict(mi, array: np.ndarray, raw: bool) -> dict:
    return {
        "type": "bitmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(array, np.float32)),
        "raw": raw,
        "filter_type": "nearest",
    }


def bsdf_dict(mi, material) -> dict:
    """Mitsuba `principled` BSDF (alpha = roughness^2, F0 = 0.04 for dielectrics) for a Material."""
    albedo_map, rough_map = material.albedo_map(), material.roughness_map()
    base = (
        _texture_dict(mi, albedo_map, raw=True)
        if albedo_map is not None
        else {"type": "rgb", "value": list(material.albedo)}
    )
    rough = _texture_dict(mi, rough_map[..., None], raw=True) if rough_map is not None else material.roughness
    return {"type": "principled", "base_color": base, "roughness": rough, "metallic": material.metallic}


def write_mesh_ply(mesh: dict, path) -> None:
    """A `Shape.mesh` ({"vertices": (V, 3), "faces": (F, 3)}) as a binary PLY file (float32 vertices)."""
    import trimesh

    vertices = np.asarray(mesh["vertices"], np.float64)
    faces = np.asarray(mesh["faces"], np.int64)
    trimesh.Trimesh(vertices, faces, process=False).export(path)


def scene_dict(room: Room, max_depth: int = 8, mesh_dir=None) -> dict:
    """The room as a Mitsuba scene dict (path integrator; sensors are built per view). Mesh shapes are
    written as PLY files into the folder `mesh_dir` (required when the room has one), which must exist
    until the dict is loaded; they are flat-shaded (face normals), as the G-buffers' geometric normals."""
    import mitsuba as mi

    sc: dict = {"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth)}}
    bsdfs = [bsdf_dict(mi, m) for m in room.materials]
    for k, s in enumerate(room.shapes):
        if s.kind == "mesh":
            if mesh_dir is None:
                raise ValueError(f"shape {k} ({s.role}) is a mesh: scene_dict needs a mesh_dir to write it to")
            path = os.path.join(str(mesh_dir), f"shape_{k:03d}.ply")
            write_mesh_ply(s.mesh, path)
            sc[f"shape_{k:03d}_{s.role}"] = {
                "type": "ply",
                "filename": path,
                "face_normals": True,
                "bsdf": bsdfs[s.material],
            }
            continue
        d = {"type": s.kind, "to_world": mi.ScalarTransform4f(np.asarray(s.to_world)), "bsdf": bsdfs[s.material]}
        if s.emission is not None:
            d["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": list(s.emission)}}
        sc[f"shape_{k:03d}_{s.role}"] = d
    if room.sky is not None:
        sc["sky"] = {"type": "envmap", "bitmap": mi.Bitmap(_sky_bitmap(room.sky))}
    return sc


def load_scene(room: Room, max_depth: int = 8):
    import mitsuba as mi

    # Both flags keep the emitter order fixed: parallel loading registers objects in thread-timing order
    # and the optimiser's shape merging reorders shapes (and so their area lights) from run to run. The
    # emitter order decides which random numbers pick which light, so either would break "same seed,
    # same pixels" across processes.
    with tempfile.TemporaryDirectory(prefix="invrender_meshes_") as mesh_dir:  # read while loading
        return mi.load_dict(scene_dict(room, max_depth, mesh_dir), parallel=False, optimize=False)


def render_view(scene, camera: Camera, width: int, height: int, spp: int, seed: int) -> np.ndarray:
    """(H, W, 3) float32 HDR radiance from Mitsuba's perspective sensor (box filter, path tracing)."""
    import mitsuba as mi

    sensor = mi.load_dict(
        {
            "type": "perspective",
            "fov": float(camera.fov_x_deg),
            "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=camera.origin, target=camera.target, up=[0, 1, 0]),
            "sampler": {"type": "independent", "sample_count": int(spp)},
            "film": {"type": "hdrfilm", "width": int(width), "height": int(height), "rfilter": {"type": "box"}},
        }
    )
    img = mi.render(scene, sensor=sensor, spp=int(spp), seed=int(seed) & 0x7FFFFFFF)
    return np.array(img, dtype=np.float32)[..., :3]


# ----------------------------------------------------------------------------------------------------
# Ray queries


JIT_ALIGN_BYTES = 64


def _jit_columns(points: np.ndarray) -> list[np.ndarray]:
    """The columns of (N, 3) `points` as contiguous float32 arrays that start on a 64-byte boundary.

    Dr.Jit reads numpy input in place and writes the buffer's alignment into the kernel it compiles, so
    numpy's varying allocation alignment made every call a new kernel to compile (and the kernel cache
    never hit): compilation was over half of `synthesize`. Aligned copies keep one kernel per scene.
    """
    points = np.asarray(points, np.float32)
    step = JIT_ALIGN_BYTES // points.itemsize
    columns = []
    for values in points.T:
        buf = np.empty(len(values) + step, np.float32)
        start = (-buf.ctypes.data % JIT_ALIGN_BYTES) // points.itemsize
        column = buf[start : start + len(values)]
        column[:] = values
        columns.append(column)
    return columns


def intersect(scene, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
    """First hits of world-space rays (N, 3): t (N,) metres (inf on a miss), shading normal (N, 3) world,
    base colour (N, 3), roughness (N,), metallic (N,), lamp (N,) bool (the hit shape is an emitter)."""
    if _is_vectorised():
        return _intersect_vectorised(scene, origins, directions)
    rows = [_intersect_one(scene, o, d) for o, d in zip(origins, directions, strict=True)]
    return {k: np.stack([r[k] for r in rows]) for k in rows[0]} if rows else {}


def _intersect_vectorised(scene, origins, directions):
    import drjit as dr
    import mitsuba as mi

    o, d = _jit_columns(origins), _jit_columns(directions)  # kept alive until the results are read
    ray = mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d))
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    bsdf = si.bsdf(ray)
    fields = {
        "hit": valid,
        "t": si.t,
        "normal": si.sh_frame.n,
        "albedo": bsdf.eval_attribute_3("base_color", si, valid),
        "roughness": bsdf.eval_attribute_1("roughness", si, valid),
        "metallic": bsdf.eval_attribute_1("metallic", si, valid),
        "lamp": valid & (si.shape.emitter() != None),  # noqa: E711 (drjit pointer compare)
    }
    dr.eval(*fields.values())  # one kernel, whatever the number of rays
    dtypes = {"hit": bool, "t": np.float64, "normal": np.float64, "lamp": bool}
    out = {k: _to_numpy(v, dtypes.get(k, np.float32)) for k, v in fields.items()}
    out["t"][~out["hit"]] = np.inf
    return out


def _to_numpy(values, dtype) -> np.ndarray:
    """An evaluated Dr.Jit array, (N,) or a 3-vector as (N, 3), copied out one channel at a time.

    Converting a 3-vector whole runs a kernel that interleaves its channels with N and 2N written into
    the code, so each new ray count compiled the whole computation again."""
    import drjit as dr

    if dr.size_v(values) == 3:
        return np.stack([np.array(values[k], dtype=dtype) for k in range(3)], axis=-1)
    return np.array(values, dtype=dtype).reshape(-1)


def _intersect_one(scene, o, d):
    import mitsuba as mi

    ray = mi.Ray3f(mi.ScalarPoint3f(*map(float, o)), mi.ScalarVector3f(*map(float, d)))
    si = scene.ray_intersect(ray)
    if not si.is_valid():
        z3 = np.zeros(3)
        return {
            "hit": False,
            "t": np.inf,
            "normal": z3,
            "albedo": z3.astype(np.float32),
            "roughness": np.float32(0),
            "metallic": np.float32(0),
            "lamp": False,
        }
    bsdf = si.bsdf(ray)
    return {
        "hit": True,
        "t": float(si.t),
        "normal": np.array(si.sh_frame.n, float),
        "albedo": np.array(bsdf.eval_attribute_3("base_color", si, True), np.float32),
        "roughness": np.float32(bsdf.eval_attribute_1("roughness", si, True)),
        "metallic": np.float32(bsdf.eval_attribute_1("metallic", si, True)),
        "lamp": si.shape.emitter() is not None,
    }


def radiance(
    scene, origins: np.ndarray, directions: np.ndarray, spp: int, seed: int, batch_rays: int = 1 << 21
) -> tuple[np.ndarray, np.ndarray]:
    """Incident radiance L_i(o, -d) arriving at o from direction d, i.e. radiance along the ray o + t d,
    path traced with `spp` independent samples per ray. Returns mean (N, 3) and its standard error (N, 3)."""
    n = len(origins)
    mean, stderr = np.zeros((n, 3)), np.zeros((n, 3))
    rays_per_chunk = max(1, batch_rays // spp)
    for c, start in enumerate(range(0, n, rays_per_chunk)):
        sl = slice(start, min(n, start + rays_per_chunk))
        o = np.repeat(np.asarray(origins[sl], np.float32), spp, axis=0)
        d = np.repeat(np.asarray(directions[sl], np.float32), spp, axis=0)
        samples = (_trace_vectorised if _is_vectorised() else _trace_loop)(scene, o, d, seed * 1000003 + c)
        samples = samples.reshape(-1, spp, 3)
        mean[sl] = samples.mean(1)
        stderr[sl] = samples.std(1, ddof=1) / math.sqrt(spp) if spp > 1 else np.inf
    return mean, stderr


def radiance_difference(
    scene_a, scene_b, origins: np.ndarray, directions: np.ndarray, spp: int, seed: int, batch_rays: int = 1 << 21
) -> tuple[np.ndarray, np.ndarray]:
    """Radiance along the same rays in two scenes, a minus b, path traced with `spp` samples per ray drawn
    from the same random streams in both (one seed, the same rays): where a path never meets what differs
    between the scenes, its two samples are equal and their difference is exactly 0, so the difference
    is far less noisy than two independent renders' (in the vectorised variants: the scalar loop draws one
    stream for all rays in turn, so there the two renders part after the first path that differs and the
    difference is unbiased but noisier). Returns mean (N, 3) and the standard error (N, 3) of the
    per-sample differences."""
    n = len(origins)
    mean, stderr = np.zeros((n, 3)), np.zeros((n, 3))
    rays_per_chunk = max(1, batch_rays // spp)
    trace = _trace_vectorised if _is_vectorised() else _trace_loop
    for c, start in enumerate(range(0, n, rays_per_chunk)):
        sl = slice(start, min(n, start + rays_per_chunk))
        o = np.repeat(np.asarray(origins[sl], np.float32), spp, axis=0)
        d = np.repeat(np.asarray(directions[sl], np.float32), spp, axis=0)
        stream = seed * 1000003 + c
        diff = (trace(scene_a, o, d, stream) - trace(scene_b, o, d, stream)).reshape(-1, spp, 3)
        mean[sl] = diff.mean(1)
        stderr[sl] = diff.std(1, ddof=1) / math.sqrt(spp) if spp > 1 else np.inf
    return mean, stderr


def _trace_vectorised(scene, o, d, seed):
    import drjit as dr
    import mitsuba as mi

    sampler = mi.load_dict({"type": "independent"})
    # an opaque seed is a kernel parameter; a plain int is a literal in the code, one kernel per seed
    sampler.seed(dr.opaque(mi.UInt32, int(seed) & 0x7FFFFFFF), len(o))
    o, d = _jit_columns(o), _jit_columns(d)  # kept alive until the results are read
    ray = mi.RayDifferential3f(mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d)))
    L, _, _ = scene.integrator().sample(scene, sampler, ray)
    dr.eval(L)
    return _to_numpy(L, np.float64)


def _trace_loop(scene, o, d, seed):
    import mitsuba as mi

    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(int(seed) & 0x7FFFFFFF, 1)
    integ = scene.integrator()
    out = np.zeros((len(o), 3))
    for k in range(len(o)):
        ray = mi.RayDifferential3f(mi.Ray3f(mi.ScalarPoint3f(*map(float, o[k])), mi.ScalarVector3f(*map(float, d[k]))))
        L, _, _ = integ.sample(scene, sampler, ray)
        out[k] = np.array(L, float)[:3]
        sampler.advance()
    return out
