"""Training and evaluation of one cell: prepare -> loop (fit) -> evaluate, logged to one MLflow run by run.py."""
