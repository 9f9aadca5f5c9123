"""Apply a trained run's model to new frames: the MLflow pyfunc loader, frame and video readers, ``track``.

Apart from training (docs/architecture.md): this package imports training's network
and evaluation functions, never the other way round. No VTK on its import path.
"""
