#!/usr/bin/env bash
# Runs the README's "Without kernel CAN: socketcand over TCP" commands as written, in a clean
# clone of this repository (its committed HEAD): the README's `cargo build --release` must
# build every binary the commands then run, and each command must do its job:
#   - the bridge listens, the simulator connects, `rollbase run` drives seed 000 to its goal
#     (exit 0) with a finished recording, the monitor connects and ends on Ctrl-C (exit 0);
#   - the bridge and the simulator stop cleanly on SIGTERM (exit 0).
# `rollbase run` gets a second try only after a stale-feedback fault (a host stall), on a
# fresh simulator, as the real-time cli tests do; both summaries are printed.
#
# Usage: scripts/readme-socketcand.sh
# The release build reuses $CARGO_TARGET_DIR (default: this checkout's target/) for the
# dependencies; the two binaries are deleted first, so they must come from the clone's build.
# The bridge listens on the README's fixed port (29536): run this where nothing else uses it,
# e.g. in a network namespace of its own (.ci/run: `unshare -n`).
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$repo/target}"
work="$(mktemp -d)"
pids=()
cleanup() {
    for p in "${pids[@]}"; do kill -9 "$p" 2>/dev/null || true; done
    rm -rf "$work"
}
trap cleanup EXIT

git clone --quiet "$repo" "$work/rollbase"
cd "$work/rollbase"
# The README's commands refer to ./target/release/…: point it at the build directory.
ln -s "$CARGO_TARGET_DIR" target

# The block under the heading, as written.
block="$(awk '/^## Without kernel CAN: socketcand over TCP/{f=1} f&&/^```sh/{c=1;next} c&&/^```/{exit} c' README.md)"
[ -n "$block" ] || { echo "README: no sh block under 'Without kernel CAN: socketcand over TCP'"; exit 1; }
echo "README block:"
echo "$block" | sed 's/^/    /'
mapfile -t lines < <(echo "$block" | sed 's/[[:space:]]*#.*$//' | sed '/^[[:space:]]*$/d')
[ "${lines[0]}" = "cargo build --release" ] || { echo "the block does not start with 'cargo build --release': ${lines[0]}"; exit 1; }

rm -f "$CARGO_TARGET_DIR/release/rollbase" "$CARGO_TARGET_DIR/release/rollbase-sim"
echo "== ${lines[0]}"
${lines[0]}
for b in rollbase rollbase-sim; do
    [ -x "target/release/$b" ] || { echo "cargo build --release did not build $b"; exit 1; }
done

logs="$work/logs"
mkdir -p "$logs"
bridge_pid=""
sim_pid=""
sim_cmd=""
for ((k = 1; k < ${#lines[@]}; k++)); do
    line="${lines[$k]}"
    echo "== $line"
    case "$line" in
    *"&")
        cmd="${line%&}"
        bash -c "exec $cmd" >"$logs/$k.out" 2>"$logs/$k.err" &
        pid=$!
        pids+=("$pid")
        case "$cmd" in
        *" bridge"*) bridge_pid=$pid ;;
        *rollbase-sim*) sim_pid=$pid sim_cmd=$cmd ;;
        esac
        # As a person typing the next line: the server is up before its client starts.
        sleep 1
        kill -0 "$pid" || { echo "'$cmd' ended at once:"; cat "$logs/$k.err"; exit 1; }
        ;;
    *" monitor "*)
        # The monitor runs until stopped: watch the bus while the simulator answers nothing
        # (no controller on it now), so a few seconds, then SIGINT as Ctrl-C.
        set +e
        timeout --preserve-status -s INT 5 bash -c "exec $line" >"$logs/$k.out" 2>"$logs/$k.err"
        rc=$?
        set -e
        [ "$rc" -eq 0 ] || { echo "monitor exited $rc:"; cat "$logs/$k.err"; exit 1; }
        ;;
    *)
        set +e
        timeout 300 bash -c "exec $line" >"$logs/$k.out" 2>"$logs/$k.err"
        rc=$?
        set -e
        tail -n 25 "$logs/$k.out" "$logs/$k.err"
        # A host stall of 16 ms (4 cycles) is a stale-feedback fault by design, and a shared
        # CI machine has them (the landing CI of e5ad6ff: 335 deadline misses, compute p99
        # 2.5 ms against 0.19 ms here). As the real-time cli tests and the VM stage do, the
        # run gets one more try after exactly that fault, on a fresh simulator (the faulted
        # run left the plant where it stopped); the first run's recording is kept aside and
        # both summaries are printed. Any other failure, or a second fault, is final.
        if [ "$rc" -ne 0 ] && [ -n "$sim_cmd" ] && grep -q "sent no valid feedback" "$logs/$k.out" "$logs/$k.err"; then
            echo "== '$line' ended in a stale-feedback fault (a host stall, above); once more on a fresh simulator"
            [ -f run.mcap ] && mv run.mcap "$logs/run-attempt1.mcap"
            kill -TERM "$sim_pid"
            wait "$sim_pid" || true
            bash -c "exec $sim_cmd" >"$logs/sim2.out" 2>"$logs/sim2.err" &
            sim_pid=$!
            pids+=("$sim_pid")
            sleep 1
            kill -0 "$sim_pid" || { echo "'$sim_cmd' ended at once:"; cat "$logs/sim2.err"; exit 1; }
            set +e
            timeout 300 bash -c "exec $line" >"$logs/$k.retry.out" 2>"$logs/$k.retry.err"
            rc=$?
            set -e
            tail -n 25 "$logs/$k.retry.out" "$logs/$k.retry.err"
        fi
        [ "$rc" -eq 0 ] || { echo "'$line' exited $rc"; exit 1; }
        ;;
    esac
done

# The recording of `rollbase run … --record run.mcap` is finished: plot reads it (CRCs, index).
[ -f run.mcap ] || { echo "run.mcap was not written"; exit 1; }
target/release/rollbase plot run.mcap --out "$work/plots" >/dev/null

# The bridge and the simulator stop cleanly (exit 0) on SIGTERM, as a service manager stops them.
for p in "$sim_pid" "$bridge_pid"; do
    [ -n "$p" ] || continue
    kill -TERM "$p"
    set +e
    wait "$p"
    rc=$?
    set -e
    [ "$rc" -eq 0 ] || { echo "process $p exited $rc after SIGTERM"; cat "$logs"/*.err; exit 1; }
done
echo "README socketcand commands: pass"
