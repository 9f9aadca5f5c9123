"""The metrics every FINISHED run logs (shared by the CPU and the GPU training tests), and its constant params."""

METRIC_NAMES = ("pos_l2", "pos_l2_mm", "rot_l2", "de", "ce", "geodesic")
PER_SOURCE = [f"{scope}.{m}.{s}" for scope in ("pair", "acc") for m in METRIC_NAMES for s in ("mean", "std")]
EXPECTED = (
    PER_SOURCE
    + [f"{ref}.{k}" for ref in ("zero_motion", "train_mean") for k in PER_SOURCE]
    + [f"{ref}traj.{m}.{s}" for ref in ("", "zero_motion.", "train_mean.")
       for m in ("ctf", "ctf_mm", "ate", "ate_mm", "rpe_trans", "rpe_rot", "drift") for s in ("mean", "std")]
    + ["test.n_pairs", "test.n_trajectories", "n_params", "val_best.loss", "pred.std.pos", "pred.std.rot",
       "pred.std_ratio.pos", "pred.std_ratio.rot", "train.steps", "train.pairs_seen", "train.epochs",
       "train.best_step", "train.pairs_per_s", "train.train_pairs"]
)
# The evaluation's constants: params since issue 36 (runs logged before have them as metrics), never metrics now.
EVAL_PARAMS = ("eval.ctf_position", "eval.ctf_position_mm", "eval.ctf_angle", "eval.rpe_gap")
