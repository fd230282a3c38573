"""The papers' procedures as plans (TOML), installed as the package data ``hilbench.plans``."""
