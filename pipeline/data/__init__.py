"""Datasets: file formats, the synthetic generator, preprocessing into shards, datamodules."""
