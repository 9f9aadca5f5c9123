#!/usr/bin/env bash
# The README's main command from a fresh clone, timed per part: what the main-job results files record
# (benchmarks/results/main-job-*.json: clone_venv_s, torch_s, project_s, sweep_s, report_s, total_s).
#
#   benchmarks/main_job_phases.sh REPO DIR      # REPO: a path or URL to clone; DIR: a new folder for the clone
#
# It clones REPO into DIR, reads the code block after `<!-- main-command -->` in DIR/README.md (its steps, one
# per line or joined by `&&`; comments and its `git clone` line left out), splits it at its `&&` and runs the
# parts one after another in one shell (the venv's activation carries over), printing the seconds of each part
# and a timestamp, then the phases as the results files name them. Nothing is installed outside DIR. Stops at the
# first part that fails (its exit status).
set -euo pipefail
if [ $# -ne 2 ]; then
    echo "usage: $0 REPO DIR   (clone REPO into the new folder DIR and time the README's main command there)" >&2
    exit 2
fi
repo=$1
dir=$2
if [ -e "$dir" ]; then
    echo "$0: $dir exists: give a new folder (the measurement is from a fresh clone)" >&2
    exit 2
fi
now() { date +%s.%N; }
calc() { awk "BEGIN { printf \"%.3f\", $* }"; }
t0=$(now)
git clone -q "$repo" "$dir"
cd "$dir"
# the main command's code block: one step per line (or one line of steps joined by &&); comments and the
# `git clone ... && cd ...` line (done above) dropped, the steps joined by && to be split below
cmd=$(awk '/<!-- main-command -->/{getline; f=1; next} f && /^```/{exit} f' README.md \
      | sed -e 's/[[:space:]]*#.*$//' -e '/^[[:space:]]*$/d' -e '/^git clone /d' | awk 'BEGIN{ORS=""} NR>1{print " && "} {print}')
if [ -z "$cmd" ]; then
    echo "$0: no line after <!-- main-command --> in $dir/README.md" >&2
    exit 2
fi
t_clone=$(now)
printf '%-60s %8.1f s  %s\n' "git clone" "$(calc "$t_clone - $t0")" "$(date -Is)"
declare -a names secs
prev=$t_clone
# the parts of the command, split at ` && `
IFS=$'\n' read -r -d '' -a parts < <(printf '%s' "$cmd" | awk 'BEGIN{RS=" && "} {print}' && printf '\0') || true
for part in "${parts[@]}"; do
    [ -n "$part" ] || continue
    eval "$part"
    t=$(now)
    s=$(calc "$t - $prev")
    printf '%-60s %8.1f s  %s\n' "${part:0:60}" "$s" "$(date -Is)"
    names+=("$part")
    secs+=("$s")
    prev=$t
done
total=$(calc "$prev - $t0")
# the phases as the results files name them: clone_venv_s = clone + venv; torch_s = the part installing torch;
# project_s = the part installing the project; install_s = torch_s + project_s (never the clone or the venv)
clone_venv=$(calc "$t_clone - $t0")
torch=0; project=0; sweep=0; report=0
for i in "${!names[@]}"; do
    case "${names[$i]}" in
        *"-m venv"*|". .venv/bin/activate"*) clone_venv=$(calc "$clone_venv + ${secs[$i]}") ;;
        *"install torch"*) torch=${secs[$i]} ;;
        *"install -e"*) project=${secs[$i]} ;;
        *"bronchopose sweep"*) sweep=${secs[$i]} ;;
        *"bronchopose report"*) report=${secs[$i]} ;;
    esac
done
echo
printf 'clone_venv_s %.1f\ntorch_s %.1f\nproject_s %.1f\ninstall_s %.1f\nsweep_s %.1f\nreport_s %.1f\ntotal_s %.1f\n' \
    "$clone_venv" "$torch" "$project" "$(calc "$torch + $project")" "$sweep" "$report" "$total"
