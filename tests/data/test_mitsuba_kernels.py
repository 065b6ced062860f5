"""Ray queries compile once per scene: later calls with other seeds and other arrays reuse the kernels.

A literal seed or the alignment of a numpy buffer written into the kernel made every call a new kernel,
and compiling them was over half of `synthesize`'s time.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.data.synth import mitsuba_backend as mb
from pipeline.data.synth.scene import RoomConfig, generate_room


def test_jit_columns_are_aligned_contiguous_copies():
    rng = np.random.default_rng(0)
    for n in (1, 7, 1000):
        points = rng.normal(size=(n, 3))  # float64, as the callers pass them
        columns = mb._jit_columns(points)
        assert len(columns) == 3
        for k, column in enumerate(columns):
            assert column.dtype == np.float32 and column.flags.c_contiguous
            assert column.ctypes.data % mb.JIT_ALIGN_BYTES == 0
            np.testing.assert_array_equal(column, points[:, k].astype(np.float32))


def _rays(seed: int, n: int = 257):
    rng = np.random.default_rng(seed)
    origins = rng.uniform(0.5, 1.5, (n, 3))
    directions = rng.normal(size=(n, 3))
    return origins, directions / np.linalg.norm(directions, axis=1, keepdims=True)


def test_ray_queries_reuse_their_kernels_across_calls(mitsuba_variant):
    if mitsuba_variant.startswith("scalar"):
        pytest.skip("the scalar variant compiles no kernels")
    import drjit as dr

    room, _, _ = generate_room(3, 1, RoomConfig())
    scene = mb.load_scene(room, 3)
    mb.radiance(scene, *_rays(0), spp=4, seed=1)
    mb.intersect(scene, *_rays(0))
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # clears it
        for call in range(1, 4):  # new seeds, new (differently aligned) numpy arrays
            mb.radiance(scene, *_rays(call, 257 + call), spp=4, seed=1 + call)
            mb.intersect(scene, *_rays(call, 300 + call))
        launched = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert launched, "no kernel was launched"
    compiled = [k["hash"] for k in launched if not (k["cache_hit"] or k["cache_disk"])]
    assert not compiled, f"{len(compiled)} of {len(launched)} kernels compiled anew: {compiled}"
