"""hilbench: a hardware-in-the-loop bench for smart-material actuators."""

__version__ = "0.1.0"
