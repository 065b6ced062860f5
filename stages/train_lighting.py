"""DVC stage `train_lighting`: LightNet with HDR light and MC re-rendering losses -> outputs/train_lighting."""

import hydra
from omegaconf import DictConfig

from pipeline.systems.lighting_stage import run_train_lighting


def run(cfg: DictConfig) -> dict[str, float]:
    return run_train_lighting(cfg)


@hydra.main(config_path="../conf", config_name="train_lighting", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
