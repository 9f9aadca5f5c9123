"""Apply a trained run's model to new frames: the MLflow pyfunc loader, frame and video readers, ``track``.

Apart from training (DESIGN.md §5): this package imports training's network
and evaluation functions, never the other way round. No VTK on its import path.
"""
