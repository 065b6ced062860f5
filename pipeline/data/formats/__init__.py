"""Readers and writers for on-disk formats."""
