"""The lighting ground truth of one view, typed (DESIGN.md section 4; layouts in `ops.envmap`).

On disk (`interiorverse.read_light`, preprocess shards) it is a flat dict of arrays keyed
`surf_*` / `free_*`; everything that trains on or scores against it uses these classes instead, so the
keys live here and in the writer only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.ops.camera import RAY_OFFSET_M


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
        """(directions (P, T, 3), radiance (P, T, 3)) with T = R * C texels per probe."""
        return self.directions.flatten(1, 2), self.radiance.flatten(1, 2)


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
    """Rays of the lighting ground truth of a batch of views, M of them: origin, direction, radiance
    (M, 3); image (M,) long, the view each belongs to; pixel (M, 2) the surface probe's pixel (-1 for
    free points)."""

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
) -> ProbeRays | None:
    """Rays of `kind` probes over a batch's views: per view `probes` random probes and per probe `texels`
    random texels (None = all, in order, drawing no random number). None when no view has such probes."""
    parts = []
    for b, light in enumerate(lights):
        pr = light.kind(kind)
        if not len(pr):
            continue
        d, r = pr.texels()
        P, T = d.shape[:2]
        pi = torch.arange(P) if probes is None else torch.randperm(P, generator=generator)[:probes]
        if texels is None:
            ti = torch.arange(T).expand(len(pi), T)
        else:
            ti = torch.stack([torch.randperm(T, generator=generator)[:texels] for _ in range(len(pi))])
        pi, ti = pi.to(d.device), ti.to(d.device)  # random numbers from the (CPU) generator, indices where the data is
        n_t = ti.shape[1]
        gather = ti[..., None].expand(-1, -1, 3)
        px = pr.pixel[pi] if pr.pixel is not None else torch.full((len(pi), 2), -1, dtype=torch.long, device=d.device)
        parts.append(
            ProbeRays(
                origin=pr.origins()[pi].repeat_interleave(n_t, 0),
                direction=torch.gather(d[pi], 1, gather).flatten(0, 1),
                radiance=torch.gather(r[pi], 1, gather).flatten(0, 1),
                image=torch.full((len(pi) * n_t,), b, dtype=torch.long, device=d.device),
                pixel=px.repeat_interleave(n_t, 0),
            )
        )
    return ProbeRays.cat(parts)
