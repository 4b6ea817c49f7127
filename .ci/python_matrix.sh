#!/usr/bin/env bash
# The README's commands on each Python a user may have (3.11, 3.12, 3.13 by default; SAGRASP_PYTHONS="3.12"
# picks others): a copy of this checkout, a fresh .venv in it, the README's install lines as written, the
# pretrained policy on the twin, then a short train, evaluate, export and a deploy of the export.
# The training budget is the only departure from the README (1,024 env steps instead of 10M).
# Each interpreter is python3.X on PATH or pyenv's; a missing one fails the run (say SAGRASP_PYTHONS to skip it).
# On 3.12 and 3.13 pip builds pybullet from source the first time (no wheel on the index for them; a C++
# compiler needed, 7-12 min on 2 cores), then reuses the wheel from its cache.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
pythons="${SAGRASP_PYTHONS:-3.11 3.12 3.13}"
tiny=(--total-steps 1024 --no-progress --set eval.num_cycles=1 --set eval.episodes=8 --set ppo.num_envs=64
      --set ppo.num_epochs=1 --set ppo.num_minibatches=1 --set env.task.max_steps=50)
deploy_args=(--target-cam -147 -77 1374 --units mm --obstacle sphere -40 -160 1300 30)

find_python() {
    local v="$1" candidate
    for candidate in "$(command -v "python$v" || true)" "$HOME"/.pyenv/versions/"$v".*/bin/python; do
        if [ -n "$candidate" ] && [ -x "$candidate" ] && "$candidate" -c "import sys; assert sys.version.startswith('$v.')" 2>/dev/null; then
            echo "$candidate"
            return 0
        fi
    done
    return 1
}

step() {  # step NAME [--ok CODES] COMMAND...: run it, say how long it took, stop the run on any other exit status
    local name="$1" start=$SECONDS ok="0" status=0
    shift
    if [ "$1" = "--ok" ]; then ok="$2"; shift 2; fi
    "$@" > "$log.$name" 2>&1 || status=$?
    if [[ " ${ok//,/ } " != *" $status "* ]]; then
        echo "python matrix: $version: '$name' failed (exit $status); its output:"
        tail -n 40 "$log.$name"
        exit 1
    fi
    echo "  $version $name: $((SECONDS - start)) s (exit $status)"
}

summary=()
for version in $pythons; do
    python="$(find_python "$version")" || { echo "python matrix: no Python $version on this machine"; exit 1; }
    work="$(mktemp -d)"
    log="$work/log"
    clone="$work/sagrasp_jax"
    mkdir -p "$clone"
    (cd "$repo" && git ls-files -co --exclude-standard -z | xargs -0 tar -c --no-recursion -f - 2>/dev/null) | tar -x -C "$clone"
    leg_start=$SECONDS
    cd "$clone"
    # "Try the trained policy" as the README writes it
    step venv "$python" -m venv .venv
    # shellcheck disable=SC1091
    . .venv/bin/activate
    step install-twin pip install -q ".[twin]"
    step deploy-pretrained python -m sagrasp_jax.deploy --policy pretrained "${deploy_args[@]}" --json
    python - "$log.deploy-pretrained" <<'EOF'
import json, sys
report = json.load(open(sys.argv[1]))
assert report["outcome"] == "success" and report["held"] is True, report
EOF
    step rehearse python -m sagrasp_jax.deploy.rehearse --policy pretrained --episodes 3 --condition robot
    # "Train your own": the README's install line, then its commands with a tiny budget
    step install-train pip install -q --no-compile -e ".[train]"
    step train python -m sagrasp_jax.train --preset cpu-quick --algo sa-ppo --seed 0 --out runs/quick "${tiny[@]}"
    step evaluate python -m sagrasp_jax.evaluate --run runs/quick --episodes 64 --condition robot
    step export python -m sagrasp_jax.export --run runs/quick --out policy/
    test -f policy/policy.npz && test -f policy/policy.onnx
    # a 1,024-step policy may not reach the cube: exit 1 with a report is a run that worked
    step deploy-export --ok 0,1 python -m sagrasp_jax.deploy --policy policy/policy.npz "${deploy_args[@]}" --json
    python - "$log.deploy-export" <<'EOF'
import json, sys
assert json.load(open(sys.argv[1]))["outcome"] in ("success", "timeout", "collision", "refused")
EOF
    deactivate
    cd "$repo"
    summary+=("$version ($("$python" -c 'import platform; print(platform.python_version())'), $((SECONDS - leg_start)) s)")
    rm -rf "$work"
done
echo "python matrix: README commands ran on ${summary[*]}"
