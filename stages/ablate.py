"""DVC stage `ablate`: one conf/ablation/ preset at one seed -> outputs/ablate/<preset>-s<seed>, reports."""

import hydra
from omegaconf import DictConfig

from pipeline.runs.ablate import run


@hydra.main(config_path="../conf", config_name="ablate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
