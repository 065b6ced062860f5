"""DVC stage `train_material`: MaterialNet on the preprocess shards -> outputs/train_material, reports."""

import hydra
from omegaconf import DictConfig

from pipeline.runs.train_material import run


@hydra.main(config_path="../conf", config_name="train_material", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
