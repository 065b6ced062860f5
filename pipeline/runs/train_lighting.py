"""Stage `train_lighting`: LightNet trained with the HDR light loss and the MC re-rendering loss, scored
on the test split beside content-blind baselines and oracles (`systems.lighting_baselines`).

Writes under `out_dir` (the DVC out): model.pt (the LightNet export with the weights `test_weights`
names), the same bytes for the same seed; beside it, under `checkpoint_dir(out_dir)`
(outputs/checkpoints/train_lighting): best.ckpt and last.ckpt (Lightning; they name the MLflow run, for
`resume=last`); under `report_dir`: metrics.json, test_views.csv (`view_rows`), rerender.png, envmaps.png.
"""

from __future__ import annotations

from omegaconf import DictConfig

from pipeline.systems.lighting_training import train_lighting


def run(cfg: DictConfig) -> dict[str, float]:
    return train_lighting(cfg)
