"""DVC stage `finetune` (see conf/finetune.yaml)."""

import hydra
from omegaconf import DictConfig

from pipeline.runs.finetune import run


@hydra.main(config_path="../conf", config_name="finetune", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
