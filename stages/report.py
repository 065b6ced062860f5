"""DVC stage `report`: every ablation and stage gathered into reports/report (ablations.md, pareto.png, summary.md)."""

import hydra
from omegaconf import DictConfig

from pipeline.runs.report import run


@hydra.main(config_path="../conf", config_name="report", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
