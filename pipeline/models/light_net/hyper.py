"""Hypernetwork: a global scene feature -> the weights of a small MLP, applied per scene (batched)."""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F


class HyperMLP(nn.Module):
    """Emits the weights of an MLP with layer sizes `sizes` (e.g. [in, 64, 64, out]) from a feature (B, F).

    forward(feature) -> list of (W (B, out, in), b (B, out)) per layer; `apply(params, x, scene)` runs the
    generated MLP on points x (N, in) of scene index `scene` (N,) with ReLU between layers and no final
    activation. The emitted weights start at a fan-in scaled initialisation (a small head on a normalised
    feature), so the generated MLP is well conditioned from the first step.
    """

    def __init__(self, feature_dim: int, sizes: list[int], hidden: int = 128):
        super().__init__()
        if len(sizes) < 2:
            raise ValueError(f"sizes={sizes}: need at least input and output sizes")
        self.sizes = list(sizes)
        self.trunk = nn.Sequential(nn.Linear(feature_dim, hidden), nn.ReLU(inplace=True))
        self.heads = nn.ModuleList()
        for cin, cout in zip(sizes[:-1], sizes[1:], strict=True):
            head = nn.Linear(hidden, cout * cin + cout)
            nn.init.normal_(head.weight, std=0.1 / math.sqrt(hidden))
            with torch.no_grad():  # bias = a fixed ordinary initialisation of the generated layer
                w0 = torch.empty(cout, cin)
                nn.init.kaiming_uniform_(w0, a=math.sqrt(5))
                head.bias.copy_(torch.cat([w0.flatten(), torch.zeros(cout)]))
            self.heads.append(head)

    def forward(self, feature: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        h = self.trunk(feature)
        params = []
        for head, cin, cout in zip(self.heads, self.sizes[:-1], self.sizes[1:], strict=True):
            flat = head(h)
            params.append((flat[:, : cout * cin].view(-1, cout, cin), flat[:, cout * cin :]))
        return params

    @staticmethod
    def run_generated(
        params: list[tuple[torch.Tensor, torch.Tensor]], x: torch.Tensor, scene: torch.Tensor
    ) -> torch.Tensor:
        """Run the generated MLP of scene[i] on x[i]: x (N, in), scene (N,) long -> (N, out).

        Points are grouped by scene and each group goes through its scene's layers as one dense matrix
        product; gathering a weight matrix per point instead moves N*out*in floats per layer and is
        memory bound (see pipeline.bench.light_net).
        """
        n_scenes = params[0][0].shape[0]
        order = torch.argsort(scene, stable=True)
        counts = torch.bincount(scene, minlength=n_scenes).tolist()
        groups = []
        for s, xs in enumerate(torch.split(x[order], counts)):
            for k, (w, b) in enumerate(params):
                xs = torch.addmm(b[s], xs, w[s].t())
                if k < len(params) - 1:
                    xs = F.relu(xs)
            groups.append(xs)
        inverse = torch.empty_like(order)
        inverse[order] = torch.arange(len(order), device=order.device)
        return torch.cat(groups).index_select(0, inverse)
