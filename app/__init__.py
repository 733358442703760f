"""App layer: renderers, camera and overlays that read the engine's state."""
