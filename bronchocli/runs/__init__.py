"""MLflow run tracking: how runs are opened, recorded, found, shown and ended.

* ``client`` — the MLflow client of a config's store: set-up, reachability, busy-database retries, experiment;
* ``sqlite_busy`` — SQLite stores wait ``runs.busy_timeout_s`` on a lock (MLflow's own engine);
* ``relocation`` — copied or moved projects read and write their own artifacts;
* ``records`` — tags, params and metrics a run carries, and finding runs again by tags;
* ``processes`` — which process runs a run, and ending runs whose process died;
* ``contract`` — what the sweep and the training engine agree on (result, stop exceptions, checkpoints, GPU share);
* ``cores`` — how many CPU threads each training process takes: its share beside the project's other processes;
* ``views`` — what a run shows in the MLflow UI (comparable params, headline metrics, description, the link);
* ``parents`` — the parent runs of sweeps and studies.

Import from the module that holds a name (``from bronchocli.runs.client import client_for``): each name has
one home. "Tracking" alone means camera tracking in this project (``track``, ``odometry``).
"""
