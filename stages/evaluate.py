"""DVC stage `evaluate` (see conf/evaluate.yaml)."""

import hydra
from omegaconf import DictConfig

from pipeline.systems.benchmark_stages import run_evaluate


def run(cfg: DictConfig) -> dict[str, float]:
    return run_evaluate(cfg)


@hydra.main(config_path="../conf", config_name="evaluate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
