"""`python -m pipeline.bench.light_energy`: where the trained LightNet's normalised light error comes from.

Over one probe's T texels, with m^ and m the predicted and true texel means (per channel), the squared
error splits exactly into an energy part and a placement part (the cross term sums to zero):

    sum_t (L^_t - L_t)^2 = T (m^ - m)^2 + sum_t ((L^_t - m^) - (L_t - m))^2

Summed over the test probes and divided once by the summed sum_t L_t^2 (pooled, so it differs from the
stage's per-batch mean nMSE by under 0.01), the two parts add up to LightNet's nMSE. The probe-mean
oracle (the true mean at every texel) has no energy part, so a model beats it only if its placement
part plus its energy part is below the oracle's placement part, which is fixed by the data.
On the test views of the exported LightNet (the frozen MaterialNet's G-buffers, as `train_lighting`
tests it), at surface probes and free points separately, this reports:
- the nMSE of LightNet, of the probe-mean oracle, of LightNet's own probe means at every texel (its
  energy without its placement) and of LightNet rescaled per probe and channel to the true mean (its
  placement with the true energy; the rescaling scales its deviations too, so this is not its placement
  part), and the energy and placement parts of LightNet's;
- per ray class (SSRT hit, uncertain hit, miss): the predicted energy over the true energy (sum of
  radiance) and the class's contribution to the nMSE (in nMSE units: the classes' contributions add up
  to LightNet's nMSE);
- the single gain that would minimise the pooled nMSE and the nMSE it gives, and the same with one gain
  per ray class. They are fitted on the test views themselves: a diagnostic of bias, not a calibration.
Needs the trained exports (`dvc repro train_lighting`). Writes reports/bench/light_energy.json and a PNG
(predicted against true probe means, log-log; the nMSE of each predictor beside the oracle).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import publish
from pipeline.bench.light_net import evaluation_system
from pipeline.data.lighting import ViewLighting, probe_rays
from pipeline.metrics.lighting import ray_classes

KINDS = ViewLighting.KINDS
RAY_CLASSES = ("hit", "uncertain", "miss")  # the keys of `ray_classes`, each added by every EnergyTally.add
PREDICTORS = ("lightnet", "probe_mean_oracle", "lightnet_energy_only", "lightnet_placement_true_energy")


def energy_placement_split(pred: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
    """pred, target (P, T, 3): P probes of T texels. Sums over all probes, texels and channels (0-dim):
    `error` sum (L^ - L)^2, its `energy` part T sum_p (m^_p - m_p)^2 and `placement` part (the texels'
    deviations from their probe means compared), and `target` sum L^2 (the nMSE denominator)."""
    pm, tm = pred.mean(1, keepdim=True), target.mean(1, keepdim=True)
    T = pred.shape[1]
    return {
        "error": ((pred - target) ** 2).sum(),
        "energy": T * ((pm - tm) ** 2).sum(),
        "placement": (((pred - pm) - (target - tm)) ** 2).sum(),
        "target": (target**2).sum(),
    }


def predictor_errors(pred: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
    """Summed squared error (0-dim) of each of PREDICTORS on pred, target (P, T, 3). Rescaling to the true
    energy divides by the predicted probe mean; a probe predicted black keeps its black texels."""
    pm, tm = pred.mean(1, keepdim=True), target.mean(1, keepdim=True)
    gain = torch.where(pm > 0, tm / pm.clamp(min=1e-12), torch.zeros_like(pm))
    candidates = {
        "lightnet": pred,
        "probe_mean_oracle": tm.expand_as(target),
        "lightnet_energy_only": pm.expand_as(target),
        "lightnet_placement_true_energy": pred * gain,
    }
    return {name: ((c - target) ** 2).sum() for name, c in candidates.items()}


CLASS_FIELDS = ("nmse_contribution", "predicted_over_true_energy", "ray_fraction")


def class_parts(summary: dict, fields=CLASS_FIELDS) -> dict:
    """{class: {field: value}} of an `EnergyTally.summary` for every ray class, the fields given."""
    return {c: {f: summary["classes"][c][f] for f in fields} for c in RAY_CLASSES}


class EnergyTally:
    """Running sums over views of one probe kind: the split, the predictors' errors, and per ray class the
    predicted and true radiance sums, the squared error and the terms of its best gain (the classes
    partition the texels, so the terms of the best single gain are their sums)."""

    def __init__(self):
        self.sums: dict[str, float] = {}
        self.probe_means: list[np.ndarray] = []  # (P, 2): predicted, true probe mean (channel average)

    def _add(self, key: str, value) -> None:
        self.sums[key] = self.sums.get(key, 0.0) + float(value)

    def add(self, pred: torch.Tensor, target: torch.Tensor, hit: torch.Tensor, u: torch.Tensor) -> None:
        """pred, target (P, T, 3) float64; hit, u (P, T) of LightNet's query (`ray_classes`)."""
        for k, v in energy_placement_split(pred, target).items():
            self._add(k, v)
        for k, v in predictor_errors(pred, target).items():
            self._add(f"error/{k}", v)
        for name, sel in ray_classes(hit, u).items():
            self._add(f"class/{name}/rays", sel.sum())
            self._add(f"class/{name}/pred", pred[sel].sum())
            self._add(f"class/{name}/target", target[sel].sum())
            self._add(f"class/{name}/error", ((pred[sel] - target[sel]) ** 2).sum())
            self._add(f"class/{name}/pred_target", (pred[sel] * target[sel]).sum())
            self._add(f"class/{name}/pred_pred", (pred[sel] ** 2).sum())
        self.probe_means.append(torch.stack([pred.mean((1, 2)), target.mean((1, 2))], 1).numpy())

    def summary(self) -> dict:
        s = self.sums
        if not s or s["target"] <= 0:
            raise ValueError("no probe texel with light: nothing to split (are the test views' probes empty?)")
        den = s["target"]

        def total(term: str) -> float:
            return sum(s[f"class/{c}/{term}"] for c in RAY_CLASSES)

        pt_all, pp_all, rays_all = total("pred_target"), total("pred_pred"), total("rays")
        gain = pt_all / max(pp_all, 1e-30)
        out = {
            "nmse": {name: s[f"error/{name}"] / den for name in PREDICTORS},
            "lightnet_energy_part": s["energy"] / den,
            "lightnet_placement_part": s["placement"] / den,
            "oracle_placement_part": s["error/probe_mean_oracle"] / den,
            "best_gain": gain,
            "nmse_at_best_gain": (gain**2 * pp_all - 2 * gain * pt_all + den) / den,
            "classes": {},
        }
        # the classes split the texels, so each class's best gain is fitted alone and their errors add up
        error_at_class_gains = 0.0
        for name in RAY_CLASSES:
            target = s[f"class/{name}/target"]
            error = s[f"class/{name}/error"]
            pt, pp = s[f"class/{name}/pred_target"], s[f"class/{name}/pred_pred"]
            class_gain = pt / pp if pp > 0 else 1.0
            error_at_class_gains += error + (class_gain**2 - 1) * pp - 2 * (class_gain - 1) * pt  # sum (g p - t)^2
            out["classes"][name] = {
                "ray_fraction": s[f"class/{name}/rays"] / max(rays_all, 1),
                "predicted_over_true_energy": s[f"class/{name}/pred"] / target if target > 0 else None,
                "nmse_contribution": error / den,
                "best_gain": class_gain,
            }
        out["nmse_at_best_class_gains"] = error_at_class_gains / den
        means = np.concatenate(self.probe_means)
        out["probes"] = int(len(means))
        ratio = means[:, 0] / np.maximum(means[:, 1], 1e-30)
        out["median_predicted_over_true_probe_mean"] = float(np.median(ratio))
        return out


@torch.no_grad()
def tally(model_path: Path, data_dir: str, material_path: Path, split: str = "test") -> dict[str, EnergyTally]:
    """An EnergyTally per probe kind over every view of `split`, every texel at the evaluation's stratified
    directions (`probe_rays` without sampling), LightNet queried as `train_lighting` tests it."""
    from pipeline.data.datamodules import InteriorVerseDataModule

    system = evaluation_system(model_path, material_path)
    dm = InteriorVerseDataModule(data_dir, batch_size=4, lighting=True)
    dm.setup("test" if split == "test" else "fit")
    return tally_batches(system, tqdm(dm.plain_loader(split), desc=f"light energy ({split})"))


@torch.no_grad()
def tally_batches(system, batches) -> dict[str, EnergyTally]:
    """An EnergyTally per probe kind of a `LightingSystem` over `batches` (the datamodule's collated
    views): every texel at the evaluation's stratified directions, LightNet queried as the system tests it."""
    tallies = {kind: EnergyTally() for kind in KINDS}
    for batch in batches:
        gen = system.eval_generator()
        fov = system.fov(batch)
        gb = system.gbuffers(batch)
        ctx = system.net.encode(batch["im"], gb["depth"], fov, normal=gb["normal"])
        for kind in KINDS:
            rays = probe_rays(batch["light"], kind)
            if rays is None:
                continue
            q = system.query(ctx, gb, fov, rays, gen)
            start = 0
            for light in batch["light"]:  # rays run view by view, probe by probe, texel by texel
                P, T = light.kind(kind).texels()[1].shape[:2]
                if P == 0:
                    continue
                seg = slice(start, start + P * T)
                start += P * T
                tallies[kind].add(
                    q["radiance"][seg].view(P, T, 3).double(),
                    rays.radiance[seg].view(P, T, 3).double(),
                    q["hit"][seg].view(P, T),
                    q["u"][seg].view(P, T),
                )
            if start != len(rays):  # the views' probes must account for every ray, in probe_rays' order
                raise RuntimeError(f"{kind} probes: {start} texels split over views, {len(rays)} rays queried")
    return tallies


def run(
    model_path="outputs/train_lighting/model.pt",
    data_dir="outputs/preprocess",
    material_path="outputs/train_material/model.pt",
    split: str = "test",
) -> dict:
    missing = [str(p) for p in (model_path, material_path) if not Path(p).is_file()]
    if missing:
        raise FileNotFoundError(f"{', '.join(missing)} not found: run `dvc repro train_lighting` first")
    tallies = tally(Path(model_path), data_dir, Path(material_path), split)
    report = {"model": str(model_path), "gbuffers": f"predicted by {material_path}", "split": split}
    report["kinds"] = {kind: t.summary() for kind, t in tallies.items() if t.sums}
    report["probe_means"] = {
        kind: np.concatenate(t.probe_means).round(6).tolist() for kind, t in tallies.items() if t.probe_means
    }
    return report


def plot(report: dict, path) -> None:
    """The pooled nMSE (dimensionless) of each predictor per probe kind, and per kind LightNet's probe
    means against the true ones (radiance, log-log)."""
    kinds = list(report["kinds"])
    fig = Figure(figsize=(4.6 * (1 + len(kinds)), 4.0))
    axes = fig.subplots(1, 1 + len(kinds))
    ax = axes[0]
    width = 0.8 / max(len(kinds), 1)
    labels = ["LightNet", "probe-mean\noracle", "LightNet's\nenergy only", "LightNet at\ntrue energy"]
    for i, kind in enumerate(kinds):
        vals = [report["kinds"][kind]["nmse"][p] for p in PREDICTORS]
        ax.bar(np.arange(len(PREDICTORS)) + i * width, vals, width, label=kind)
    ax.set_xticks(np.arange(len(PREDICTORS)) + width * (len(kinds) - 1) / 2, labels, fontsize=7)
    ax.set_ylabel(f"normalised MSE ({report['split']}, pooled)")
    lo = min(v for k in kinds for v in report["kinds"][k]["nmse"].values())
    ax.set_ylim(max(0.0, lo - 0.1), None)
    ax.legend(fontsize=7)
    ax.set_title("nMSE of each predictor (axis not from 0)", fontsize=9)
    for ax, kind in zip(axes[1:], kinds, strict=True):
        m = np.asarray(report["probe_means"][kind])
        ok = (m[:, 0] > 0) & (m[:, 1] > 0)
        ax.loglog(m[ok, 1], m[ok, 0], ".", ms=2, alpha=0.4, label=f"{int(ok.sum())} probes")
        lim = [m[ok].min(), m[ok].max()]
        ax.plot(lim, lim, "k--", lw=0.8, label="predicted = true")
        if (~ok).any():
            ax.plot([], [], " ", label=f"{int((~ok).sum())} probes with a zero mean not drawn")
        k = report["kinds"][kind]
        miss = k["classes"]["miss"]["predicted_over_true_energy"]
        ax.set_title(
            f"{kind}: median predicted/true probe mean {k['median_predicted_over_true_probe_mean']:.2f}\n"
            f"on misses, predicted/true energy {'n/a' if miss is None else f'{miss:.2f}'}",
            fontsize=8,
        )
        ax.set_xlabel("true probe mean radiance")
        ax.set_ylabel("LightNet's probe mean")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="outputs/train_lighting/model.pt")
    p.add_argument("--data-dir", default="outputs/preprocess")
    p.add_argument("--material", default="outputs/train_material/model.pt", help="MaterialNet export (G-buffers)")
    p.add_argument("--split", default="test", choices=("test", "val"))
    a = p.parse_args(argv)
    report = run(a.model, a.data_dir, a.material, a.split)
    print(publish("light_energy", report, plot))


if __name__ == "__main__":
    main()
