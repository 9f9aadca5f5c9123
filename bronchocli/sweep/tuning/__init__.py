"""Tuning studies: ``bronchopose tune``'s Optuna studies, their trials run as rows of the sweep's claims table.

The room mirrors the sweep's own layout (``sweep.launch``, ``sweep.worker``):

- ``rows``: a study's trial rows by name (``<study>.trials``, ``trial-0000``, ...) and the ``StudyTask`` a worker
  is given instead of a sweep's stages (light: the sweep's command and every worker import it);
- ``launch``: ``tune`` itself: the study opened, its rows added, driven through the sweep's one driver with any
  launcher (``sweep.launch.drive``), its parent run ended; ``sweep cancel --study``;
- ``worker``: a worker over a study's rows: claim a row, run one Optuna trial for it, record the outcome;
- ``trial``: what one trial is (the search space, one MLflow run, the objective, the pruner and sampler);
- ``studies``: the studies on the shared storage (opening it, reading a study back, the best trial applied);
- ``resume``: a stopped trial's checkpoint handed to a trial that resumes it, and what ``sweep gc`` keeps.

Importing this package imports none of them (Optuna loads only where a study is opened).
"""
