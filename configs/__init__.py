"""Rig configurations (TOML), installed as the package data ``hilbench.configs``."""
