"""Monte Carlo estimate of reflected radiance, I = 1/n sum f(wo, wi_k) L_i(p, wi_k) cos / pdf(wi_k).

Estimators (docs/design.md, section 5):
  importance  the paper's: BRDF mixture sampling (GGX visible normals + cosine), `sampling.sample`
  uniform     uniform hemisphere sampling, pdf 1/(2 pi)
  li2020      Li et al. 2020's discretised hemisphere: n_theta x n_phi cell centres, uniform in theta in
              [0, pi/2] and phi, each weighted by sin(theta) dtheta dphi (pi^2/128 sin(theta) at 8 x 16)

Per-pixel sample counts may differ (adaptive sampling): samples are numbered flat, pixel by pixel, and
processed in chunks of `chunk` samples. A chunk finds its pixels from the cumulative counts, draws its
random numbers from a counter-based hash of (seed, sample number) and sums its contributions per pixel
itself; with gradients on and more than one chunk, each is checkpointed (recomputed in backward). So no
per-sample tensor outlives its chunk and memory does not grow with the sample count, and results do not
depend on the chunk size. A single chunk (a training step's few pixels) is not checkpointed: recomputing
it would run the radiance callback twice per step, and a callback that draws random numbers (LightNet's
volume samples) would draw different ones in backward than in forward.
Unbiased by construction: directions and pdf are detached, there is no clamp on the pdf, and a sample
with pdf 0 contributes exactly 0. Gradients reach albedo, roughness, metallic, normal (through f and
the cosine) and the radiance callback.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch.utils.checkpoint import checkpoint

from pipeline.ops import brdf, sampling
from pipeline.ops.frames import from_local, orthonormal_basis

RadianceFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  # (pixel index (M,), wi (M, 3)) -> (M, 3)
ESTIMATORS = ("importance", "uniform", "li2020")


def li2020_directions(n_theta: int = 8, n_phi: int = 16, dtype=torch.float32, device=None):
    """Local directions (K, 3) at cell centres of the discretised hemisphere and their solid-angle
    weights (K,) = sin(theta) * (pi/2 / n_theta) * (2 pi / n_phi)."""
    dth, dph = (math.pi / 2) / n_theta, (2 * math.pi) / n_phi
    th = (torch.arange(n_theta, dtype=dtype, device=device) + 0.5) * dth
    ph = (torch.arange(n_phi, dtype=dtype, device=device) + 0.5) * dph
    th, ph = torch.meshgrid(th, ph, indexing="ij")
    dirs = torch.stack([th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()], -1).reshape(-1, 3)
    return dirs, (th.sin() * dth * dph).reshape(-1)


def _i64(c: int) -> int:
    """A 64-bit constant as the signed int64 torch stores (two's complement)."""
    return c - (1 << 64) if c >= 1 << 63 else c


def _shr(z: torch.Tensor, k: int) -> torch.Tensor:
    """Logical right shift of int64 bit patterns (torch's >> is arithmetic on signed ints)."""
    return (z >> k) & ((1 << (64 - k)) - 1)


def counter_uniform(seed: int, index: torch.Tensor, dims: int = 3) -> torch.Tensor:
    """Uniform numbers in [0, 1) (len(index), dims) that depend only on (seed, index): a splitmix64 hash of
    the counter seed * 2^32 + index * dims + d, keeping the top 24 bits. Chunks of samples can therefore
    draw (and, in backward, redraw) their own numbers without storing any, and the result does not
    depend on how the samples were chunked."""
    x = (index.long()[:, None] * dims + torch.arange(dims, device=index.device)) + (int(seed) << 32)
    z = x + _i64(0x9E3779B97F4A7C15)
    z = (z ^ _shr(z, 30)) * _i64(0xBF58476D1CE4E5B9)
    z = (z ^ _shr(z, 27)) * _i64(0x94D049BB133111EB)
    z = z ^ _shr(z, 31)
    return _shr(z, 40).to(torch.float64) / float(1 << 24)


def allocate_samples(albedo, roughness, metallic, valid, budget: int, glossy_gain: float = 8.0) -> torch.Tensor:
    """Samples per pixel (N,) long summing to `budget` (when budget >= #valid): masked pixels get 0, every
    valid pixel at least 1, the rest in proportion to w = (1 - k_s) + k_s * min(glossy_gain, 1/roughness),
    i.e. glossy pixels (whose peaked lobes make L_i vary most across samples) get up to `glossy_gain`
    times the share of a diffuse one. Largest-remainder rounding keeps the total exact."""
    valid = valid.reshape(-1).bool()
    n_valid = int(valid.sum())
    counts = torch.zeros(valid.shape[0], dtype=torch.long, device=valid.device)
    if n_valid == 0:
        return counts
    if budget < n_valid:
        raise ValueError(f"sample budget {budget} is below the number of valid pixels {n_valid}")
    with torch.no_grad():
        ks = sampling.specular_probability(albedo[valid], metallic.reshape(-1)[valid])
        gloss = (1.0 / roughness.reshape(-1)[valid].clamp(min=1e-6)).clamp(max=glossy_gain)
        w = (1 - ks) + ks * gloss
        share = (budget - n_valid) * w / w.sum()
        base = share.floor().long()
        rest = budget - n_valid - int(base.sum())
        if rest > 0:
            base[torch.topk(share - base, rest).indices] += 1
    counts[valid] = 1 + base
    return counts


def _contributions(mode, start, stop, seed, cum, normal, wo, albedo, roughness, metallic, radiance_fn, li_dirs, li_w):
    """Samples start..stop-1 (global sample indices), each at its pixel (from the cumulative counts `cum`):
    per-pixel sums (diffuse (N, 3), specular (N, 3)) of f * L * cos / pdf over these samples."""
    sample = torch.arange(start, stop, device=normal.device)
    pix = torch.searchsorted(cum, sample, right=True) - 1
    if mode == "li2020":
        u = (sample - cum[pix]).to(normal.dtype).unsqueeze(-1).expand(-1, 3)  # index of the fixed direction
    else:
        u = counter_uniform(seed, sample).to(normal.dtype)
    n, o, a = normal[pix], wo[pix], albedo[pix]
    r, m = roughness.reshape(-1)[pix], metallic.reshape(-1)[pix]
    with torch.no_grad():
        if mode == "importance":
            wi, p = sampling.sample(u, n.detach(), o.detach(), a.detach(), r.detach(), m.detach())
            weight_num = None
        elif mode == "uniform":
            wi, p = sampling.sample_uniform(u, n.detach())
            weight_num = None
        else:  # li2020: u holds the index of the fixed direction
            k = u[:, 0].long()
            t, b = orthonormal_basis(n.detach())
            wi = from_local(li_dirs[k], t, b, n.detach())
            p = torch.ones_like(li_w[k])
            weight_num = li_w[k]
    f_d, f_s = brdf.evaluate(n, o, wi, a, r, m)
    cos = (n * wi).sum(-1).clamp(min=0)
    safe = torch.where(p > 0, p, torch.ones_like(p))
    w = torch.where(p > 0, cos / safe, torch.zeros_like(cos))
    if weight_num is not None:
        w = w * weight_num
    L = radiance_fn(pix, wi)
    # summed per pixel here, inside the (checkpointed) chunk: index_add saves its per-sample source for
    # backward, which outside the checkpoint would keep every chunk's samples alive
    zeros = torch.zeros(normal.shape[0], 3, dtype=normal.dtype, device=normal.device)
    return zeros.index_add(0, pix, f_d * L * w.unsqueeze(-1)), zeros.index_add(0, pix, f_s * L * w.unsqueeze(-1))


def estimate(
    radiance_fn: RadianceFn,
    normal,
    wo,
    albedo,
    roughness,
    metallic,
    counts: torch.Tensor | int,
    generator: torch.Generator,
    estimator: str = "importance",
    chunk: int = 1 << 16,
    li_size: tuple[int, int] = (8, 16),
    checkpoint_chunks: bool | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Reflected radiance (diffuse (N, 3), specular (N, 3)) at N shading points.

    normal, wo (N, 3) unit (view space); albedo (N, 3); roughness, metallic (N,); counts: samples per
    point (N,) long or one int for all (ignored by li2020, which uses its n_theta x n_phi cells);
    radiance_fn(pixel index (M,), wi (M, 3)) -> L_i (M, 3). Points with 0 samples return 0. `generator`
    draws the seed of the counter-based numbers (one draw per call; li2020, whose directions are fixed,
    draws none). checkpoint_chunks: recompute chunks in backward (None: only when there is more than one)."""
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator={estimator!r}: choose one of {ESTIMATORS}")
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator={generator!r}: pass a torch.Generator (no fallback to the global RNG)")
    N, dev, dt = normal.shape[0], normal.device, normal.dtype
    li_dirs = li_w = None
    if estimator == "li2020":
        li_dirs, li_w = li2020_directions(*li_size, dtype=dt, device=dev)
        counts = torch.full((N,), li_dirs.shape[0], dtype=torch.long, device=dev)
    elif isinstance(counts, int):
        counts = torch.full((N,), counts, dtype=torch.long, device=dev)
    counts = counts.to(dev)
    cum = torch.zeros(N + 1, dtype=torch.long, device=dev)
    cum[1:] = torch.cumsum(counts, 0)
    total = int(cum[-1])
    seed = int(torch.randint(0, 1 << 30, (1,), generator=generator)) if estimator != "li2020" else 0
    diffuse = torch.zeros(N, 3, dtype=dt, device=dev)
    specular = torch.zeros(N, 3, dtype=dt, device=dev)
    grads = torch.is_grad_enabled()  # the callback may hold parameters even when the G-buffers do not
    for start in range(0, total, chunk):
        args = (
            estimator,
            start,
            min(total, start + chunk),
            seed,
            cum,
            normal,
            wo,
            albedo,
            roughness,
            metallic,
            radiance_fn,
            li_dirs,
            li_w,
        )
        recompute = total > chunk if checkpoint_chunks is None else checkpoint_chunks
        if grads and recompute:  # recompute each chunk in backward: memory stays at one chunk
            d, sp = checkpoint(_contributions, *args, use_reentrant=False)
        else:
            d, sp = _contributions(*args)
        diffuse, specular = diffuse + d, specular + sp
    if estimator != "li2020":
        scale = 1.0 / counts.clamp(min=1).to(dt).unsqueeze(-1)
        diffuse, specular = diffuse * scale, specular * scale
    return diffuse, specular
