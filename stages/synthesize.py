"""DVC stage `synthesize`: procedural rooms rendered with Mitsuba 3 into outputs/synthesize."""

import hydra
from omegaconf import DictConfig

from pipeline.runs.synthesize import run


@hydra.main(config_path="../conf", config_name="synthesize", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
