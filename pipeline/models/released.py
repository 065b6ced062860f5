"""Import the authors' released checkpoints (jingsenzhu/IndoorInverseRendering, commit 1104515) as
invrender exports (`pipeline.models.export`), under the `paper` profile's architecture.

MGNet: a Lightning checkpoint of the released training module (`mgnet/trainBRDF_pl.py`), whose
`state_dict` holds `models.{encoder,albedo,normal,material,depth}.*` (a torchvision DenseNet121 and four
`DecoderDenseNet`s, `mgnet/models/network.py:52-216`) and the training-only `perceptual_loss.*` (VGG16).
A bare state dict with the same keys is accepted too. The export runs at the released 240x320 input.

Reading is weights-only (`torch.load(weights_only=True)`): a file holding anything but tensors and
plain containers is refused, and so is a file whose keys or shapes do not match, naming them. The export
is checked by reading it back before it replaces `out`, so nothing is written on failure.

Depth: the released MGNet was trained on depth divided by each view's largest depth
(`mgnet/dataLoader/__init__.py:110-111`), so its depth is relative. An imported export carries
`depth_scale` = metres at that unit (1.0 unless told otherwise: the view's farthest point 1 m away), and
`invrender predict` writes depth x depth_scale x 1000; the released test script instead divides each
prediction by its own maximum (`mgnet/testBRDF_real.py:75-76`).
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

import torch
from torch import nn

from pipeline.models.export import ExportError

# conf/model/material_net/paper.yaml (tests/models/test_released_import.py checks they agree)
PAPER_MATERIAL_NET = {
    "backbone": "densenet121",
    "layout": "mgnet",
    "decoder_widths": [512, 256, 128, 64, 64],
    "decoder_groups": [32, 16, 16, 8, 4],
    "input_norm": "clamp",
    "pretrained_path": None,
}
MGNET_INPUT_SIZE = (240, 320)  # mgnet/config.yml:4-5 (h, w)
# released keys the forward pass does not use: the training-only VGG16 of the perceptual loss
# (mgnet/models/loss.py:67-75) and DenseNet121's ImageNet classifier (network.py:55, never called)
SKIPPED_GROUPS = ("perceptual_loss", "models.encoder.densenet.classifier")


class ReleasedImportError(ExportError):
    """A released checkpoint that cannot be imported; the message names the file and the reason."""


def _listing(names, limit: int = 8) -> str:
    names = sorted(names)
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def read_weights(path: str | Path) -> dict:
    """The object in a torch file, read weights-only; refused (naming the file) when the file is missing,
    not a torch file, or holds anything but tensors and plain containers."""
    path = Path(path)
    if not path.is_file():
        raise ReleasedImportError(f"{path}: no such file")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - pickle, zip and torch errors all mean "not weights-only"
        detail = " ".join(str(exc).split())[:300]
        raise ReleasedImportError(
            f"{path}: refused: not a weights-only torch file (only tensors and plain containers are read; "
            f"{type(exc).__name__}: {detail})"
        ) from exc


def state_dict_of(path: str | Path, blob) -> dict[str, torch.Tensor]:
    """The state dict in a loaded checkpoint: a Lightning checkpoint's `state_dict` or a bare state dict."""
    if isinstance(blob, dict) and isinstance(blob.get("format"), str) and blob["format"].startswith("invrender."):
        raise ReleasedImportError(f"{path}: already an invrender export ({blob['format']}); nothing to import")
    state = blob.get("state_dict", blob) if isinstance(blob, dict) else blob
    if not isinstance(state, dict) or not state:
        raise ReleasedImportError(f"{path}: wrong kind of file: no state dict (found {type(state).__name__})")
    bad = [str(k) for k, v in state.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)]
    if bad:
        raise ReleasedImportError(f"{path}: wrong kind of file: entries that are not named tensors: {_listing(bad)}")
    return state


_DECODER = re.compile(r"models\.(albedo|normal|material|depth)\.(dconv|dgn)(\d)\.(weight|bias)$")
_FINAL = re.compile(r"models\.(albedo|normal|material|depth)\.dconvFinal\.(weight|bias)$")


def mgnet_key(key: str) -> str | None:
    """The invrender MaterialNet (`paper`) name of a released MGNet key; None for keys the forward pass
    does not use (the training-only `perceptual_loss.*` and DenseNet's ImageNet classifier); the key
    itself, unchanged, when it is not a released MGNet key (reported as unexpected)."""
    if key.startswith(tuple(p + "." for p in SKIPPED_GROUPS)):
        return None
    if key.startswith("models.encoder.densenet.features."):
        return "encoder.net." + key[len("models.encoder.densenet.") :]
    if m := _DECODER.match(key):
        head, kind, i, field = m.groups()
        return f"decoders.{head}.blocks.{int(i) - 1}.{0 if kind == 'dconv' else 1}.{field}"
    if m := _FINAL.match(key):
        return f"decoders.{m.group(1)}.head.1.{m.group(2)}"
    return key


def convert(path, state: dict[str, torch.Tensor], target: nn.Module, rename) -> tuple[dict, list[str]]:
    """(state dict for `target`, skipped released keys): every key renamed by `rename` (None = skip);
    refused, naming them, when keys are missing or unexpected or shapes differ."""
    want = target.state_dict()
    out, skipped, unexpected, shapes, seen = {}, [], [], [], set()
    for key, value in state.items():
        name = rename(key)
        if name is None:
            skipped.append(key)
        elif name not in want:
            unexpected.append(key)
        elif tuple(value.shape) != tuple(want[name].shape):
            seen.add(name)
            shapes.append(f"{key} {tuple(value.shape)} (expected {tuple(want[name].shape)})")
        else:
            seen.add(name)
            out[name] = value
    missing = [k for k in want if k not in seen]
    problems = []
    if missing:
        problems.append(f"missing keys ({len(missing)}): {_listing(missing)}")
    if unexpected:
        problems.append(f"unexpected keys ({len(unexpected)}): {_listing(unexpected)}")
    if shapes:
        problems.append(f"shape mismatches ({len(shapes)}): {_listing(shapes)}")
    if problems:
        raise ReleasedImportError(f"{path}: does not fit {type(target).__name__} (paper): " + "; ".join(problems))
    return out, skipped


def skipped_summary(skipped: list[str]) -> dict[str, int]:
    """Skipped keys counted by group: `perceptual_loss.*` (training-only VGG16), the unused ImageNet
    classifier `models.encoder.densenet.classifier.*`, else by the key's module."""
    counts: dict[str, int] = {}
    for key in skipped:
        group = next((p for p in SKIPPED_GROUPS if key.startswith(p + ".")), key.rsplit(".", 1)[0])
        counts[group + ".*"] = counts.get(group + ".*", 0) + 1
    return counts


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _write_atomically(out: str | Path, save, check) -> Path:
    """save(tmp) then check(tmp), then rename onto `out`; on any failure the temporary file is removed
    and `out` is left as it was."""
    out = Path(out)
    if out.is_dir():
        raise ReleasedImportError(f"--out {out}: is a folder; give a file name such as model.pt")
    if not out.parent.is_dir():
        raise ReleasedImportError(f"--out {out}: folder {out.parent} does not exist")
    tmp = out.with_name(f".{out.name}.part")
    try:
        save(tmp)
        check(tmp)
        os.replace(tmp, out)
    except OSError as exc:
        raise ReleasedImportError(f"--out {out}: cannot write ({exc.strerror or exc})") from exc
    finally:
        if tmp.exists():
            tmp.unlink()
    return out


def import_mgnet(ckpt: str | Path, out: str | Path, depth_scale: float = 1.0) -> dict:
    """Write the released MGNet checkpoint `ckpt` as an invrender MaterialNet export at `out` (the `paper`
    architecture, input 240x320, `depth_scale` metres per network unit). Returns a summary: the output,
    the imported tensor count and the skipped keys by prefix."""
    from pipeline.models.export import save_material_export
    from pipeline.models.material_net import MaterialNet, load_material_export

    if not (depth_scale > 0 and depth_scale < float("inf")):
        raise ReleasedImportError(f"--depth-scale {depth_scale}: must be a positive number of metres")
    ckpt = Path(ckpt)
    state = state_dict_of(ckpt, read_weights(ckpt))
    net = MaterialNet(**PAPER_MATERIAL_NET)
    converted, skipped = convert(ckpt, state, net, mgnet_key)
    net.load_state_dict(converted, strict=True)
    released = {
        "network": "mgnet",
        "file": ckpt.name,
        "sha256": _sha256(ckpt),
        "skipped": skipped_summary(skipped),
        "depth_units": "released relative depth (trained on depth / the view's largest depth) x depth_scale",
    }

    def save(tmp):
        save_material_export(tmp, PAPER_MATERIAL_NET, net, MGNET_INPUT_SIZE, depth_scale, released=released)

    def check(tmp):
        load_material_export(tmp)

    written = _write_atomically(out, save, check)
    return {"out": str(written), "imported": len(converted), "skipped": released["skipped"]}


# conf/model/light_net/paper.yaml (tests/models/test_released_import.py checks they agree); the random
# Fourier features' size is read from the checkpoint (the release does not publish it)
PAPER_LIGHT_NET = {
    "mode": "mixed",
    "k": 10.0,
    "gap_units": "window",
    "out_threshold": 0.0,
    "ssrt_compiled": True,
    "units": "image_mean",
    "local": {
        "backbone": "resnet34",
        "levels": 4,
        "encoding": "rff",
        "rff_features": 32,
        "rff_sigma": 1.0,
        "frequencies": 0,
        "hidden": 512,
        "layers": 9,
        "skips": [4],
        "activation": "relu",
        "pixel_base": False,
        "cap": None,
    },
    "out_of_view": {
        "kind": "nerf",
        "backbone": "resnet34",
        "feature_dim": None,
        "hyper": {
            "trunk": [1024, 1024],
            "head_hidden": [4096, 4096],
            "split_bias": True,
            "param_activation": "leaky_relu",
        },
        "nerf_hidden": 64,
        "nerf_layers": 3,
        "frequencies": 6,
        "pi_encoding": False,
        "activation": "relu",
        "samples": 64,
        "bounds": "sphere",
        "sphere_radius": 3.0,
        "near": 0.05,
        "far_field": False,
        "dir_frequencies": 4,
    },
}
# released random Fourier bases (lightnet/models/network/local.py:152-165) -> LocalBranch buffers
_RFF = {"Bd": "direction", "Bn": "normal", "Bkd": "kd", "Bks": "ks", "Br": "roughness"}
_LIGHT_RULES = (
    (re.compile(r"model\.encoder\.backbone\.(.+)$"), r"local.encoder.net.\1"),
    (re.compile(r"model\.mlp\.linears\.(\d+)\.(weight|bias)$"), r"local.mlp.linears.\1.\2"),
    (re.compile(r"model_global\.model\.encoder\.backbone\.(.+)$"), r"out_of_view.encoder.net.\1"),
    (
        re.compile(r"model_global\.model\.hypernet_weight\.initial_block\.(\d+)\.(.+)$"),
        r"out_of_view.hyper.trunk.\1.\2",
    ),
    (
        re.compile(r"model_global\.model\.hypernet_bias\.initial_block\.(\d+)\.(.+)$"),
        r"out_of_view.hyper.bias_trunk.\1.\2",
    ),
    (
        re.compile(r"model_global\.model\.hypernet_weight\.hyper_nets\.(\d+)\.layer\.(\d+)\.(.+)$"),
        r"out_of_view.hyper.heads.\1.\2.\3",
    ),
    (
        re.compile(r"model_global\.model\.hypernet_bias\.hyper_nets\.(\d+)\.layer\.(\d+)\.(.+)$"),
        r"out_of_view.hyper.bias_heads.\1.\2.\3",
    ),
)


def lightnet_key(key: str, mlp_layers: int = 9) -> str | None:
    """The invrender LightNet (`paper`) name of a released LightNet key (the key itself when it is not one;
    reported as unexpected). The local MLP's `output_layer` is invrender's last linear."""
    if key.startswith("model.") and key[len("model.") :] in _RFF:
        return f"local.rff_{_RFF[key[len('model.') :]]}"
    if key.startswith("model.mlp.output_layer."):
        return f"local.mlp.linears.{mlp_layers}.{key.rsplit('.', 1)[1]}"
    for pattern, repl in _LIGHT_RULES:
        if pattern.match(key):
            return pattern.sub(repl, key)
    return key


def _nerf_input_order(frequencies: int) -> torch.Tensor:
    """For each column of invrender's position encoding ([x, sin(2^k x) dim-major, cos(...)],
    `ops.encodings.fourier`), the column of the released one ([x, sin(x), cos(x), sin(2x), ...] per
    frequency, lightnet/models/network/hyper.py:6-50) that holds the same value."""
    order = list(range(3))
    for s in range(2):  # sin, cos
        for d in range(3):
            for k in range(frequencies):
                order.append(3 + 6 * k + 3 * s + d)
    return torch.tensor(order)


def _permute_rows(t: torch.Tensor, rows: int, cols: int, row_order=None, col_order=None) -> torch.Tensor:
    """A head output that is a generated (rows, cols) matrix flattened row-major, with its generated
    rows and columns reordered (the leading dimension of `t` indexes the flattened matrix)."""
    m = t.reshape(rows, cols, *t.shape[1:])
    if row_order is not None:
        m = m[row_order]
    if col_order is not None:
        m = m[:, col_order]
    return m.reshape(t.shape).contiguous()


def _released_to_invrender_lightnet(state: dict[str, torch.Tensor], kwargs: dict) -> dict[str, torch.Tensor]:
    """Reorder what invrender lays out differently, so the same weights compute the same functions:
    - local MLP input: released [direction, normal, Kd, Ks, roughness encodings, features]
      (local.py:201-239), invrender [direction, Kd, Ks, normal, roughness, features]; the first layer's
      and the skip layer's input columns are permuted;
    - generated NeRF: input encoding order (see _nerf_input_order) and output channels, released
      (r, g, b, density) (hyper.py:448-450), invrender (density, r, g, b): the rows of the hypernetwork
      heads that emit the first and the last generated layer are permuted."""
    state = dict(state)
    m = kwargs["local"]["rff_features"]
    blocks = {"direction": 0, "normal": 1, "kd": 2, "ks": 3, "roughness": 4}
    ours = ("direction", "kd", "ks", "normal", "roughness")
    enc_cols = torch.cat([torch.arange(2 * m) + 2 * m * blocks[name] for name in ours])
    w0 = state.get("model.mlp.linears.0.weight")
    if w0 is not None and w0.shape[1] >= 10 * m:
        cols = torch.cat([enc_cols, torch.arange(10 * m, w0.shape[1])])
        state["model.mlp.linears.0.weight"] = w0[:, cols].contiguous()
        for skip in kwargs["local"]["skips"]:
            key = f"model.mlp.linears.{skip + 1}.weight"
            w = state.get(key)
            hidden = kwargs["local"]["hidden"]
            if w is not None and w.shape[1] == hidden + w0.shape[1]:
                state[key] = w[:, torch.cat([torch.arange(hidden), hidden + cols])].contiguous()
    ov = kwargs["out_of_view"]
    n_in, width, layers = 3 * (2 * ov["frequencies"] + 1), ov["nerf_hidden"], ov["nerf_layers"]
    last_head = f"model_global.model.hypernet_weight.hyper_nets.{layers}.layer.4."
    first_head = "model_global.model.hypernet_weight.hyper_nets.0.layer.4."
    channels = torch.tensor([3, 0, 1, 2])  # invrender's (density, r, g, b) from released (r, g, b, density)
    for field in ("weight", "bias"):
        key = first_head + field
        if key in state and state[key].shape[0] == width * n_in:
            state[key] = _permute_rows(state[key], width, n_in, col_order=_nerf_input_order(ov["frequencies"]))
        key = last_head + field
        if key in state and state[key].shape[0] == 4 * width:
            state[key] = _permute_rows(state[key], 4, width, row_order=channels)
        key = f"model_global.model.hypernet_bias.hyper_nets.{layers}.layer.4.{field}"
        if key in state and state[key].shape[0] == 4:
            state[key] = state[key][channels].contiguous()
    return state


RELEASED_LOCAL_CAP = 100.0  # the released local MLP's output clamp (lightnet/models/network/local.py:240)


def lightnet_kwargs(state: dict[str, torch.Tensor]) -> dict:
    """The `paper` LightNet kwargs in the released units (the raw HDR image in, radiance in its units out,
    the local branch capped at `RELEASED_LOCAL_CAP`: `units=absolute`, `local.cap`), with the random
    Fourier features' size read from the checkpoint."""
    import copy

    kwargs = copy.deepcopy(PAPER_LIGHT_NET)
    kwargs["units"] = "absolute"
    kwargs["local"]["cap"] = RELEASED_LOCAL_CAP
    bd = state.get("model.Bd")
    if bd is not None and bd.ndim == 2:
        kwargs["local"]["rff_features"] = int(bd.shape[1])
    return kwargs


def import_lightnet(pth: str | Path, out: str | Path) -> dict:
    """Write the released LightNet weights `pth` (the state dict `lightnet/main_test.py:22-23` loads) as an
    invrender LightNet export at `out` (the `paper` architecture). Returns a summary as import_mgnet."""
    from pipeline.models.export import LIGHT_FORMAT, _save, read_export
    from pipeline.models.light_net import LightNet

    pth = Path(pth)
    state = state_dict_of(pth, read_weights(pth))
    if all(k.startswith("module.") for k in state):  # saved from nn.DataParallel
        state = {k[len("module.") :]: v for k, v in state.items()}
    kwargs = lightnet_kwargs(state)
    net = LightNet(**kwargs)
    layers = kwargs["local"]["layers"]
    converted, skipped = convert(
        pth, _released_to_invrender_lightnet(state, kwargs), net, lambda k: lightnet_key(k, layers)
    )
    net.load_state_dict(converted, strict=True)
    released = {"network": "lightnet", "file": pth.name, "sha256": _sha256(pth)}
    names = {k: tuple(v.shape) for k, v in net.state_dict().items()}

    def check(tmp):
        blob = read_export(tmp, LIGHT_FORMAT)
        if {k: tuple(v.shape) for k, v in blob["state_dict"].items()} != names:
            raise ReleasedImportError(f"{tmp}: the written export does not read back")

    # export._save: save_light_export's fields plus the provenance
    written = _write_atomically(
        out, lambda tmp: _save(tmp, LIGHT_FORMAT, net, light_net=kwargs, released=released), check
    )
    return {"out": str(written), "imported": len(converted), "skipped": skipped_summary(skipped)}
