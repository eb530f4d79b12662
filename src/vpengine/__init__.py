"""vpengine: one vision foundation model per frame, its features shared on the device with many task heads."""

__version__ = "0.1.0"
