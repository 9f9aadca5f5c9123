"""A real single-node Slurm cluster for the tests: munged, slurmctld and slurmd started by hand, stopped by PID.

Debian's ``slurm-wlm`` and ``munge`` packages (``.ci/run`` installs them); no
systemd, no cgroups, no accounting daemon. The node has two fake GPUs
(``gres.conf``: ``Name=gpu File=/dev/tty[0-1]``), so Slurm sets
``CUDA_VISIBLE_DEVICES`` per task as it does on a real GPU node. Everything
lives in one folder under the system temp directory (not pytest's ``tmp_path``:
its mode 700 parents are not traversable by the munge user). Clients find the
cluster through ``SLURM_CONF``.

Gotchas this encodes (issue 20): the munge key is mode 400 and owned by munge,
its socket folder world-traversable; ``slurmctld -i`` ignores stale state;
``proctrack/linuxproc`` + ``task/none`` avoid cgroups; ``NodeHostname=localhost
NodeAddr=127.0.0.1`` with ``slurmd -N``; ``DefMemPerCPU`` so jobs share the node;
``SlurmdParameters=config_overrides`` lets the node declare more CPUs than the
machine has (tasks here mostly wait on a database, not on the CPU).
"""

from __future__ import annotations

import os
import pwd
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

NODE = "bronchonode"
PARTITION = "debug"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class SlurmCluster:
    root: Path
    conf: Path
    env: dict[str, str]
    pids: dict[str, int] = field(default_factory=dict)
    _held: dict[str, float] = field(default_factory=dict)  # requeued job -> when release_held first saw it

    def run(self, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        return subprocess.run(list(args), env=self.env, capture_output=True, text=True, check=check, timeout=60)

    def node_state(self) -> str:
        out = self.run("sinfo", "-h", "-N", "-n", NODE, "-o", "%T", check=False)
        return out.stdout.strip()

    def jobs(self) -> list[dict[str, str]]:
        """Every job in the queue: id, array task, state, name, reason."""
        out = self.run("squeue", "-h", "-r", "-o", "%i|%A|%K|%T|%j|%r").stdout
        keys = ("id", "job", "task", "state", "name", "reason")
        return [dict(zip(keys, line.split("|"))) for line in out.splitlines() if line.strip()]

    def wait_idle_queue(self, limit: float = 120.0) -> None:
        """Wait (bounded) until no job is left in the queue."""
        end = time.monotonic() + limit
        while self.jobs():
            if time.monotonic() > end:
                raise AssertionError(f"Slurm jobs still queued after {limit:g} s: {self.jobs()}")
            time.sleep(0.2)

    def release_held(self, settle_s: float = 3.0) -> None:
        """A requeued job waits ``cred_expire`` (120 s, Reason=BeginTime): start it after ``settle_s`` instead.

        Not at once: slurmd revokes the killed instance's credential with a one-second resolution and refuses
        a new credential from the same second ("Killing non-startable batch JobId=3: Job credential revoked",
        the job then ends with exit code 1 and leaves the queue). Slurm's own wait exists for this; a few
        seconds are enough on one node."""
        now = time.monotonic()
        held = {j["id"] for j in self.jobs() if j["state"] == "PENDING" and j["reason"] == "BeginTime"}
        self._held = {k: v for k, v in self._held.items() if k in held}
        for job in held:
            since = self._held.setdefault(job, now)
            if now - since >= settle_s:
                self.run("scontrol", "update", f"JobId={job}", "StartTime=now", check=False)

    def cancel_all(self) -> None:
        self.run("scancel", "-u", pwd.getpwuid(os.getuid()).pw_name, check=False)

    def log(self, name: str) -> str:
        path = self.root / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""


def _write_config(root: Path, cpus: int, gpus: int) -> tuple[Path, Path]:
    munge_dir = root / "munge"
    for sub in ("munge", "state", "spool", "log"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    os.chmod(root, 0o755)
    os.chmod(munge_dir, 0o755)
    socket_path = munge_dir / "munge.socket.2"
    conf = root / "slurm.conf"
    conf.write_text(f"""\
ClusterName=bronchotest
SlurmctldHost=localhost(127.0.0.1)
SlurmctldPort={_free_port()}
SlurmdPort={_free_port()}
AuthType=auth/munge
AuthInfo=socket={socket_path}
CredType=cred/munge
SlurmUser=root
SlurmdUser=root
StateSaveLocation={root}/state
SlurmdSpoolDir={root}/spool
SlurmctldPidFile={root}/slurmctld.pid
SlurmdPidFile={root}/slurmd.pid
SlurmctldLogFile={root}/slurmctld.log
SlurmdLogFile={root}/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
SchedulerType=sched/backfill
SchedulerParameters=sched_interval=1,sched_min_interval=0,batch_sched_delay=0,bf_interval=1
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SlurmdParameters=config_overrides
GresTypes=gpu
ReturnToService=2
KillWait=15
MinJobAge=2
InactiveLimit=0
DefMemPerCPU=100
MaxArraySize=1001
NodeName={NODE} NodeHostname=localhost NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={cpus * 400} Gres=gpu:{gpus} State=UNKNOWN
PartitionName={PARTITION} Nodes={NODE} Default=YES MaxTime=INFINITE State=UP
""")
    (root / "gres.conf").write_text(f"NodeName={NODE} Name=gpu File=/dev/tty[0-{gpus - 1}]\n")
    return conf, munge_dir


def _start_munge(munge_dir: Path) -> int:
    key = munge_dir / "munge.key"
    key.write_bytes(os.urandom(1024))
    munge = pwd.getpwnam("munge")
    for p in (munge_dir, key):
        os.chown(p, munge.pw_uid, munge.pw_gid)
    os.chmod(key, 0o400)
    pidfile = munge_dir / "munged.pid"
    cmd = ["munged", f"--key-file={key}", f"--socket={munge_dir / 'munge.socket.2'}", f"--pid-file={pidfile}",
           f"--log-file={munge_dir / 'munged.log'}", f"--seed-file={munge_dir / 'munged.seed'}"]
    if os.getuid() == 0:
        cmd = ["runuser", "-u", "munge", "--", *cmd]
    subprocess.run(cmd, check=True, capture_output=True, timeout=30)
    return int(pidfile.read_text().strip())


def _wait(predicate, what: str, limit: float) -> None:
    end = time.monotonic() + limit
    while not predicate():
        if time.monotonic() > end:
            raise RuntimeError(f"Slurm test cluster: gave up waiting for {what}")
        time.sleep(0.1)


def start_cluster(cpus: int = 4, gpus: int = 2) -> SlurmCluster:
    """Start munged, slurmctld and slurmd; returns once the node is idle."""
    root = Path(tempfile.mkdtemp(prefix="bronchopose-slurm-", dir="/tmp"))
    conf, munge_dir = _write_config(root, cpus, gpus)
    env = {**os.environ, "SLURM_CONF": str(conf)}
    cluster = SlurmCluster(root, conf, env)
    try:
        cluster.pids["munged"] = _start_munge(munge_dir)
        subprocess.run(["slurmctld", "-i", "-f", str(conf)], env=env, check=True, capture_output=True, timeout=30)
        _wait(lambda: (root / "slurmctld.pid").is_file() and (root / "slurmctld.pid").read_text().strip(),
              "slurmctld's pid file", 30)
        cluster.pids["slurmctld"] = int((root / "slurmctld.pid").read_text())
        subprocess.run(["slurmd", "-N", NODE, "-f", str(conf)], env=env, check=True, capture_output=True, timeout=30)
        _wait(lambda: (root / "slurmd.pid").is_file() and (root / "slurmd.pid").read_text().strip(),
              "slurmd's pid file", 30)
        cluster.pids["slurmd"] = int((root / "slurmd.pid").read_text())
        _wait(lambda: cluster.node_state() == "idle", "the node to be idle", 60)
    except BaseException:
        logs = "\n".join(cluster.log(n) for n in ("slurmctld", "slurmd"))
        stop_cluster(cluster)
        raise RuntimeError(f"could not start the Slurm test cluster in {root}:\n{logs[-3000:]}") from None
    return cluster


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def stop_cluster(cluster: SlurmCluster, keep: bool = False) -> None:
    """Cancel what is left, stop the daemons by PID (TERM, then KILL after a bounded wait), remove the folder."""
    if "slurmctld" in cluster.pids:
        cluster.cancel_all()
    for name in ("slurmd", "slurmctld", "munged"):
        pid = cluster.pids.get(name)
        if pid is None or not _alive(pid):
            continue
        os.kill(pid, signal.SIGTERM)
        end = time.monotonic() + 15
        while _alive(pid) and time.monotonic() < end:
            time.sleep(0.1)
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)
    if not keep:
        shutil.rmtree(cluster.root, ignore_errors=True)


# -- the services a real cluster's sweep talks to: a PostgreSQL of its own, an MLflow tracking server ----------


@dataclass
class Postgres:
    """A PostgreSQL instance of the test's own (initdb + pg_ctl as the ``postgres`` user, trust auth on loopback):
    stopping it touches no other session's database. ``url(db)`` is a SQLAlchemy URL (psycopg 3)."""

    root: Path
    port: int
    bin: Path

    def _ctl(self, *args: str) -> subprocess.CompletedProcess:
        cmd = [str(self.bin / "pg_ctl"), "-D", str(self.root / "data"), *args]
        if os.getuid() == 0:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=True)

    def start(self) -> None:
        self._ctl("-l", str(self.root / "postgres.log"), "-o", f"-p {self.port} -k {self.root} -h 127.0.0.1",
                  "-w", "start")

    def stop(self) -> None:
        self._ctl("-m", "fast", "-w", "stop")

    def url(self, db: str = "postgres") -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/{db}"


def start_postgres() -> Postgres:
    """initdb in a folder the ``postgres`` user can reach (not pytest's mode-700 tmp_path), start on a free port."""
    versions = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"))
    if not versions:
        raise RuntimeError("no PostgreSQL server binaries under /usr/lib/postgresql")
    root = Path(tempfile.mkdtemp(prefix="bronchopose-pg-", dir="/tmp"))
    os.chmod(root, 0o755)
    if os.getuid() == 0:
        pg = pwd.getpwnam("postgres")
        os.chown(root, pg.pw_uid, pg.pw_gid)
    init = [str(versions[-1]), "-D", str(root / "data"), "-A", "trust", "-U", "postgres", "--no-sync"]
    if os.getuid() == 0:
        init = ["runuser", "-u", "postgres", "--", *init]
    subprocess.run(init, capture_output=True, text=True, timeout=120, check=True)
    instance = Postgres(root, _free_port(), versions[-1].parent)
    instance.start()
    return instance


def stop_postgres(instance: Postgres) -> None:
    try:
        instance.stop()
    except subprocess.CalledProcessError:
        pass
    shutil.rmtree(instance.root, ignore_errors=True)


@dataclass
class MlflowServer:
    process: subprocess.Popen
    url: str
    log: Path


def start_mlflow_server(backend: str, artifacts: Path, python: str) -> MlflowServer:
    """``mlflow server`` on loopback with ``backend`` (a PostgreSQL URL) and served artifacts; returns once it
    answers /health."""
    port = _free_port()
    log = artifacts.parent / f"mlflow-server-{port}.log"
    cmd = [python, "-m", "mlflow", "server", "--backend-store-uri", backend, "--serve-artifacts",
           "--artifacts-destination", str(artifacts), "--host", "127.0.0.1", "--port", str(port), "--workers", "1"]
    proc = subprocess.Popen(cmd, stdout=open(log, "w"), stderr=subprocess.STDOUT,  # noqa: SIM115 - the server's
                            env={**os.environ, "MLFLOW_DISABLE_TELEMETRY": "true"})
    url = f"http://127.0.0.1:{port}"

    def up() -> bool:
        if proc.poll() is not None:
            raise RuntimeError(f"mlflow server exited: {log.read_text()[-2000:]}")
        try:
            urllib.request.urlopen(url + "/health", timeout=2).close()
            return True
        except OSError:
            return False

    _wait(up, "the MLflow server", 120)
    return MlflowServer(proc, url, log)


def stop_mlflow_server(server: MlflowServer) -> None:
    server.process.terminate()
    try:
        server.process.wait(timeout=20)
    except subprocess.TimeoutExpired:
        server.process.kill()
