"""DVC stage `edit`: object insertion and material editing scored against Mitsuba -> reports/edit."""

import hydra
from omegaconf import DictConfig

from pipeline.runs.edit import run


@hydra.main(config_path="../conf", config_name="edit", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
