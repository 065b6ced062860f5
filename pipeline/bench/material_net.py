"""`python -m pipeline.bench.material_net`: MaterialNet speed and accuracy per backbone on the CPU.

For each backbone: parameter count; inference images/s (batch 1) and training step time (batch 8,
forward + backward + AdamW step) at 160x120 and 320x240, medians side by side in one run; and the
test-split metrics after a short training of equal wall-clock time on the preprocessed `tiny` data.
Writes reports/bench/material_net.json and a PNG of accuracy vs inference time.
"""

from __future__ import annotations

import argparse

import torch
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter
from tqdm import tqdm

from pipeline.bench.common import median_seconds, publish
from pipeline.models.material_net import MaterialNet, parameter_count

BACKBONES = ("small", "resnet34", "densenet121")


def _config(backbone: str, overrides=()):
    from pipeline.bench.common import compose

    return compose("train_material", [f"model/material_net={backbone}", *overrides])


def speed(backbone: str, resolutions, repeats: int) -> list[dict]:
    cfg = _config(backbone)
    torch.manual_seed(0)
    net = MaterialNet(**{k: v for k, v in cfg.model.material_net.items()})
    opt = torch.optim.AdamW(net.parameters(), 1e-4)
    rows = []
    for H, W in resolutions:
        x1, x8 = torch.rand(1, 3, H, W), torch.rand(8, 3, H, W)
        net.eval()
        with torch.no_grad():
            infer = median_seconds(lambda x=x1: net(x), repeats)
        net.train()

        def step(x=x8):
            out = net(x)
            loss = sum(v.mean() for v in out.values())
            opt.zero_grad()
            loss.backward()
            opt.step()

        train = median_seconds(step, repeats)
        rows.append(
            {
                "height": H,
                "width": W,
                "inference_seconds": infer,
                "images_per_second": 1.0 / infer,
                "train_step_seconds_batch8": train,
            }
        )
    return rows


def short_training(backbone: str, data_dir: str, seconds: float) -> dict:
    """Train for `seconds` of wall clock with the stage's system and data, then score the test split."""
    import lightning as L

    from pipeline.systems.material import METRICS
    from pipeline.systems.material_training import build_datamodule, build_system

    cfg = _config(backbone, [f"data_dir={data_dir}", "trainer.max_epochs=1000", "figure_every=0"])
    L.seed_everything(0, verbose=False)
    system, dm = build_system(cfg), build_datamodule(cfg)
    trainer = L.Trainer(
        max_time={"seconds": seconds},
        max_epochs=1000,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        limit_val_batches=0,
        gradient_clip_val=1.0,
    )
    trainer.fit(system, datamodule=dm)
    trainer.test(system, datamodule=dm, verbose=False)
    out = {m: float(trainer.callback_metrics[f"test/{m}"]) for m in METRICS}
    out.update({"train_seconds": seconds, "steps": trainer.global_step, "epochs": trainer.current_epoch})
    return out


def run(
    backbones=BACKBONES,
    resolutions=((120, 160), (240, 320)),
    repeats: int = 3,
    train_seconds: float = 120.0,
    data_dir: str = "outputs/preprocess",
) -> dict:
    rows = []
    for backbone in tqdm(backbones, desc="material_net bench"):
        cfg = _config(backbone)
        row = {
            "backbone": backbone,
            "parameters": parameter_count(MaterialNet(**{k: v for k, v in cfg.model.material_net.items()})),
            "speed": speed(backbone, resolutions, repeats),
        }
        if train_seconds > 0:
            row["accuracy"] = short_training(backbone, data_dir, train_seconds)
        rows.append(row)
    return {"threads": torch.get_num_threads(), "data_dir": data_dir, "results": rows}


def plot(report: dict, path) -> None:
    """Test error per metric against inference milliseconds per image (log scale), one point per backbone."""
    rows = [r for r in report["results"] if "accuracy" in r]
    keys = ("albedo_mse", "normal_angle_deg", "roughness_mse", "depth_log_mse")
    fig = Figure(figsize=(3.2 * len(keys), 3))
    axes = fig.subplots(1, len(keys))
    for ax, key in zip(axes, keys, strict=True):
        for r in rows:
            ms = 1e3 * r["speed"][0]["inference_seconds"]
            ax.plot(ms, r["accuracy"][key], "o")
            ax.annotate(f"{r['backbone']}\n{r['parameters'] / 1e6:.1f}M", (ms, r["accuracy"][key]), fontsize=7)
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())  # the minor labels of a short log axis overlap
        ax.set_xlabel(f"inference ms/image ({rows[0]['speed'][0]['width']}x{rows[0]['speed'][0]['height']})")
        ax.set_ylabel(f"test {key} (lower is better)")
    if rows:
        fig.suptitle(f"after {rows[0]['accuracy']['train_seconds']:.0f} s of CPU training each", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--train-seconds", type=float, default=120.0, help="per backbone; 0 skips the accuracy part")
    p.add_argument("--data-dir", default="outputs/preprocess")
    a = p.parse_args(argv)
    report = run(repeats=a.repeats, train_seconds=a.train_seconds, data_dir=a.data_dir)
    path = publish("material_net", report, plot)
    for r in report["results"]:
        s = r["speed"][0]
        print(
            f"{r['backbone']}: {r['parameters'] / 1e6:.2f}M params, {s['images_per_second']:.1f} img/s, "
            f"train step {s['train_step_seconds_batch8']:.2f} s ({s['width']}x{s['height']})"
        )
    print(path)


if __name__ == "__main__":
    main()
