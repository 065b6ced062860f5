"""Stage `train_material`: MaterialNet training -> test metrics, trivial baselines, gate, export.

Writes under `out_dir` (the DVC out): model.pt (the best weights with the network config, for `invrender
predict`), the same bytes for the same seed; beside it, under `checkpoint_dir(out_dir)`
(outputs/checkpoints/train_material): best.ckpt and last.ckpt (Lightning; they name the MLflow run,
for `resume=last`); under `report_dir`: metrics.json, test_views.csv (`test_view_scores`) and
test_maps.png.
"""

from __future__ import annotations

from omegaconf import DictConfig

from pipeline.systems.material_training import train_material


def run(cfg: DictConfig) -> dict[str, float]:
    return train_material(cfg)
