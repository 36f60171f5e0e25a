"""labrig: datasets and evaluation for dense 3D force estimation with an event-based tactile sensor."""
__version__ = "0.1.0"
