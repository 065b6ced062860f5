"""The lighting ground truth of one view, typed (docs/design.md, section 4.1; layouts in `ops.envmap`).

On disk (`interiorverse.read_light`, preprocess shards) it is a flat dict of arrays keyed
`surf_*` / `free_*`; everything that trains on or scores against it uses these classes instead, so the
keys live here and in the writer only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.ops.camera import RAY_OFFSET_M
from pipeline.ops.envmap import square_centres, texel_directions

# A predicted texel is the mean of the model's radiance over directions spread over the texel, as the
# ground truth is (docs/data.md): in evaluation the centres of a k x k grid of the texel's solid angle.
EVAL_TEXEL_STRATA = 2


@dataclass
class Probes:
    """P probes of one kind. position (P, 3) view space, metres; directions (P, R, C, 3) unit, pointing
    where light comes from; radiance (P, R, C, 3) HDR, each texel averaged over its solid angle; normal
    (P, 3) and pixel (P, 2) (row, col) for surface probes, None for free points."""

    position: torch.Tensor
    directions: torch.Tensor
    radiance: torch.Tensor
    normal: torch.Tensor | None = None
    pixel: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.position)

    def origins(self) -> torch.Tensor:
        """(P, 3) ray origins: surface probes RAY_OFFSET_M above their surface, free points where they are."""
        return self.position if self.normal is None else self.position + RAY_OFFSET_M * self.normal

    def texels(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(centre directions (P, T, 3), radiance (P, T, 3)) with T = R * C texels per probe."""
        return self.directions.flatten(1, 2), self.radiance.flatten(1, 2)

    def texel_directions(self, probe: torch.Tensor, texel: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Directions (M, S, 3) inside texels `texel` (M,) (flat index row * C + col) of probes `probe`
        (M,), uniform in solid angle for uniform u (M, S, 2) or (S, 2) in [0, 1)^2 (`ops.envmap`)."""
        R, C = self.radiance.shape[1:3]
        normal = None if self.normal is None else self.normal[probe].double()
        d = texel_directions(texel // C, texel % C, u.double(), R, C, normal)
        return d.to(self.radiance.dtype)


@dataclass
class ViewLighting:
    """Hemisphere probes at surface pixels (`surf`) and full-sphere probes at free points (`free`)."""

    surf: Probes
    free: Probes

    KINDS = ("surf", "free")

    @classmethod
    def from_arrays(cls, light: dict) -> ViewLighting:
        """From the flat dict of arrays that `interiorverse.read_light` and the shards hold."""

        def t(key, dtype=torch.float32):
            return torch.as_tensor(np.asarray(light[key]), dtype=dtype)

        surf = Probes(
            t("surf_position"), t("surf_directions"), t("surf_radiance"), t("surf_normal"), t("surf_pixel", torch.long)
        )
        return cls(surf=surf, free=Probes(t("free_position"), t("free_directions"), t("free_radiance")))

    def kind(self, name: str) -> Probes:
        if name not in self.KINDS:
            raise ValueError(f"probe kind {name!r}: choose one of {self.KINDS}")
        return getattr(self, name)


@dataclass
class ProbeRays:
    """Rays of the lighting ground truth of a batch of views, one per texel, M of them: origin, radiance
    (M, 3); direction (M, S, 3), S directions spread over the texel (`probe_rays`); image (M,) long, the
    view each belongs to; pixel (M, 2) the surface probe's pixel (-1 for free points)."""

    origin: torch.Tensor
    direction: torch.Tensor
    radiance: torch.Tensor
    image: torch.Tensor
    pixel: torch.Tensor

    @staticmethod
    def cat(parts: list[ProbeRays]) -> ProbeRays | None:
        if not parts:
            return None
        return ProbeRays(*(torch.cat([getattr(p, f) for p in parts]) for f in ProbeRays.__dataclass_fields__))

    def to(self, device) -> ProbeRays:
        return ProbeRays(*(getattr(self, f).to(device) for f in ProbeRays.__dataclass_fields__))

    def __len__(self) -> int:
        return len(self.origin)


def probe_rays(
    lights: list[ViewLighting],
    kind: str,
    probes: int | None = None,
    texels: int | None = None,
    generator: torch.Generator | None = None,
    strata: int = EVAL_TEXEL_STRATA,
) -> ProbeRays | None:
    """Rays of `kind` probes over a batch's views, with direction (M, S, 3): S directions inside each
    ray's texel, whose mean prediction is compared with the texel's (solid-angle averaged) radiance.

    Evaluation (texels None): every probe and texel in order, each with the S = strata^2 centres of a
    stratified grid over the texel; no random number is drawn. Training (texels given): per view
    `probes` random probes (None = all) and per probe `texels` random texels, each with S = 1 direction
    drawn uniformly inside its texel by `generator` (an unbiased one-sample estimate of the texel mean).
    None when no view has such probes."""
    parts = []
    for b, light in enumerate(lights):
        pr = light.kind(kind)
        if not len(pr):
            continue
        _, r = pr.texels()
        P, T = r.shape[:2]
        pi = torch.arange(P) if probes is None else torch.randperm(P, generator=generator)[:probes]
        if texels is None:
            ti = torch.arange(T).expand(len(pi), T)
        else:
            ti = torch.stack([torch.randperm(T, generator=generator)[:texels] for _ in range(len(pi))])
        n_t = ti.shape[1]
        if texels is None:
            u = square_centres(strata)
        else:
            u = torch.rand(len(pi) * n_t, 1, 2, generator=generator, dtype=torch.float64)
        direction = pr.texel_directions(
            pi.repeat_interleave(n_t).to(r.device), ti.reshape(-1).to(r.device), u.to(r.device)
        )
        pi, ti = pi.to(r.device), ti.to(r.device)  # random numbers from the (CPU) generator, indices where the data is
        gather = ti[..., None].expand(-1, -1, 3)
        px = pr.pixel[pi] if pr.pixel is not None else torch.full((len(pi), 2), -1, dtype=torch.long, device=r.device)
        parts.append(
            ProbeRays(
                origin=pr.origins()[pi].repeat_interleave(n_t, 0),
                direction=direction,
                radiance=torch.gather(r[pi], 1, gather).flatten(0, 1),
                image=torch.full((len(pi) * n_t,), b, dtype=torch.long, device=r.device),
                pixel=px.repeat_interleave(n_t, 0),
            )
        )
    return ProbeRays.cat(parts)
