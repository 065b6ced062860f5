"""DVC stage `train_lighting`: LightNet with HDR light and MC re-rendering losses -> outputs/train_lighting."""

import hydra
from omegaconf import DictConfig

from pipeline.runs.train_lighting import run


@hydra.main(config_path="../conf", config_name="train_lighting", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
