"""Hypernetwork: a global scene feature -> the weights of a small MLP, applied per scene (batched)."""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

PARAM_ACTIVATIONS = ("none", "leaky_relu")


def mlp_stack(cin: int, widths, cout: int | None = None) -> nn.Sequential:
    """Linear + ReLU per width, then an optional final Linear to `cout` (no activation)."""
    mods, c = [], cin
    for w in widths:
        mods += [nn.Linear(c, w), nn.ReLU(inplace=True)]
        c = w
    if cout is not None:
        mods.append(nn.Linear(c, cout))
    return nn.Sequential(*mods)


class HyperMLP(nn.Module):
    """Emits the weights of an MLP with layer sizes `sizes` (e.g. [in, 64, 64, out]) from a feature (B, F).

    forward(feature) -> list of (W (B, out, in), b (B, out)) per layer; `run_generated(params, x, scene)`
    runs the generated MLP on points x (N, in) of scene index `scene` (N,) with ReLU between layers and no
    final activation.

    Structure: a trunk (Linear + ReLU per width in `trunk`), then one head per generated layer (hidden
    Linear + ReLU layers `head_hidden`, then a Linear to the layer's parameters). `split_bias`: weights and
    biases come from two independent trunk-and-heads networks (the released hypernetwork: trunk 1024, 1024
    and heads 4096, 4096); `param_activation="leaky_relu"` applies LeakyReLU(0.1) to the emitted
    parameters, as released. The last Linear of each head starts at a fan-in scaled initialisation of the
    generated layer (its bias) plus a small weight, so the generated MLP is well conditioned from step one.
    """

    def __init__(
        self,
        feature_dim: int,
        sizes: list[int],
        trunk: tuple[int, ...] = (128,),
        head_hidden: tuple[int, ...] = (),
        split_bias: bool = False,
        param_activation: str = "none",
    ):
        super().__init__()
        if len(sizes) < 2:
            raise ValueError(f"sizes={sizes}: need at least input and output sizes")
        if not trunk:
            raise ValueError("hyper.trunk: need at least one trunk width")
        if param_activation not in PARAM_ACTIVATIONS:
            raise ValueError(f"hyper.param_activation={param_activation!r}: choose one of {PARAM_ACTIVATIONS}")
        self.sizes, self.split_bias, self.param_activation = list(sizes), bool(split_bias), param_activation
        layers = list(zip(sizes[:-1], sizes[1:], strict=True))
        weight_outs = [co * ci + (0 if split_bias else co) for ci, co in layers]
        self.trunk, self.heads = self._emitter(feature_dim, trunk, head_hidden, weight_outs, layers, with_w=True)
        if split_bias:
            self.bias_trunk, self.bias_heads = self._emitter(
                feature_dim, trunk, head_hidden, [co for _, co in layers], layers, with_w=False
            )

    def _emitter(self, feature_dim, trunk, head_hidden, outs, layers, with_w: bool):
        body = mlp_stack(feature_dim, trunk)
        heads = nn.ModuleList()
        for out, (cin, cout) in zip(outs, layers, strict=True):
            head = mlp_stack(trunk[-1], head_hidden, out)
            last = head[-1]
            nn.init.normal_(last.weight, std=0.1 / math.sqrt(last.in_features))
            with torch.no_grad():  # bias = a fixed ordinary initialisation of the generated layer
                w0 = torch.empty(cout, cin)
                nn.init.kaiming_uniform_(w0, a=math.sqrt(5))
                init = [w0.flatten()] if with_w else []
                if not (with_w and self.split_bias):
                    init.append(torch.zeros(cout))
                last.bias.copy_(torch.cat(init))
            heads.append(head[0] if len(head) == 1 else head)
        return body, heads

    def forward(self, feature: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        h = self.trunk(feature)
        hb = self.bias_trunk(feature) if self.split_bias else None
        params = []
        for k, (cin, cout) in enumerate(zip(self.sizes[:-1], self.sizes[1:], strict=True)):
            flat = self.heads[k](h)
            if self.split_bias:
                w, b = flat, self.bias_heads[k](hb)
            else:
                w, b = flat[:, : cout * cin], flat[:, cout * cin :]
            if self.param_activation == "leaky_relu":
                w, b = F.leaky_relu(w, 0.1), F.leaky_relu(b, 0.1)
            params.append((w.reshape(-1, cout, cin), b))
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
        counts = torch.bincount(scene, minlength=n_scenes).tolist()
        # points already grouped by scene (one image, or rays in image order) need no permutation
        grouped = len(scene) < 2 or bool((scene[1:] >= scene[:-1]).all())
        order = None if grouped else torch.argsort(scene, stable=True)
        groups = []
        for s, xs in enumerate(torch.split(x if grouped else x[order], counts)):
            if not len(xs):
                continue
            for k, (w, b) in enumerate(params):
                xs = torch.addmm(b[s], xs, w[s].t())
                if k < len(params) - 1:
                    xs = F.relu(xs)
            groups.append(xs)
        if not groups:  # no points at all
            return x.new_zeros(0, params[-1][0].shape[1])
        out = groups[0] if len(groups) == 1 else torch.cat(groups)
        if grouped:
            return out
        inverse = torch.empty_like(order)
        inverse[order] = torch.arange(len(order), device=order.device)
        return out.index_select(0, inverse)
