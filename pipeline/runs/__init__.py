"""One module per DVC stage, named after it: `run(cfg) -> dict` wires data, systems, metrics and tracking.

dvc stage = `stages/<name>.py` = `conf/<name>.yaml` = `pipeline/runs/<name>.py` = `outputs/<name>/` =
`reports/<name>/` = MLflow run name prefix.
"""
