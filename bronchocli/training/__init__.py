"""Training and evaluation engine: one grid cell -> one Lightning run -> one MLflow run."""
