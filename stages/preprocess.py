"""DVC stage `preprocess`: validate + resize an InteriorVerse-layout root into outputs/preprocess shards."""

import hydra
from omegaconf import DictConfig

from pipeline.runs.preprocess import run


@hydra.main(config_path="../conf", config_name="preprocess", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
