#!/bin/sh
# rollbase checks against a real SocketCAN vcan0 (issue 7). Runs inside the VM (busybox sh, as
# the guest's /init child) or directly on a host that has vcan0 (scripts/vcan-vm.sh --host).
# POSIX sh only.
#
# Environment:
#   ROLLBASE_BIN        directory with rollbase and rollbase-sim
#   ROLLBASE_TESTS      directory with the driver's SocketCAN test executables
#   ROLLBASE_WORK       scratch directory (captures, logs)
#   ROLLBASE_CHECKS     space-separated subset of "0 1 2 3 4 5 6 7 8" (empty: all)
#   ROLLBASE_CHECKS_AWK the capture decoder (capture.awk)
#   ROLLBASE_IP         iproute2's ip (default: ip from PATH)
#   ROLLBASE_DURATION   seconds of the seed-000 run in check 2 (default: the whole scenario)
#
# Checks (one `CHECK n: PASS|FAIL ...` line each, then `VCAN-VM-RESULT: pass|fail P/N`):
#   0  kernel CAN + can-utils: cansend -> candump round trip and cangen burst on vcan0
#   1  the driver's SocketCAN test binaries on vcan0 (none may report "skipped"), and bus-down
#      reporting: `ip link set vcan0 down` under a live `rollbase monitor --bus vcan0` and under a
#      running `rollbase run` must make them report the interface down
#   2  rollbase-sim --bus vcan0 + rollbase run --bus vcan0 --trajectory scenario:seed000 as
#      separate processes, candump -L recording beside them; the run ends in Stopped within the
#      lockstep end-to-end bounds (position < 5 mm, heading < 0.5 deg, legs < 2 mm)
#   3  the capture decoded by `rollbase monitor --candump --summary` and by capture.awk: every
#      cyclic frame's CRC and counter valid (except the one frame check 4 injects), SYNC period
#      mean within 1 % of 4 ms, exactly one SETPOINT, FEEDBACK_A and FEEDBACK_B per node per cycle
#   4  a SETPOINT with a wrong CRC injected with cansend during the check-2 run is rejected and
#      counted by the simulator, and the run is not disturbed (check-2 bounds, no module fault)
#   5  `kill -9` of the controller while the platform moves: every module stops its motors
#      within 50 ms of the first missing SETPOINT, seen in the capture (STATUS leaves `enabled`)
#   6  the CiA 402 profile: rollbase-sim --profile cia402 (8 CiA 402 drives, 4 CiA 406 encoders)
#      + rollbase run --profile cia402 on vcan0 with candump beside them: the run ends in
#      Stopped within check 2's bounds; in the capture 12 boot-ups, 12 NMT starts, no SDO abort
#      but "object does not exist" (optional plan steps), no EMCY but informational ones (error
#      register 0), and `rollbase monitor --profile cia402` describes every frame
#   7  the CiA 402 profile, `kill -9` of the controller while the platform moves: every drive
#      reports the lost master by EMCY (RPDO timeout 0x8250 or heartbeat 0x8130) within 70 ms
#      of the last RPDO and its statusword shows fault (the 0x6007 reaction)
#   8  two buses (vcan0 and vcan1, made if missing): the six-wheel example with rollbase-sim and
#      rollbase run taking one --bus each; each bus carries SYNCs and only its own wheels'
#      frames; vcan1 going down mid-run stops the whole base (the run ends in Fault within 10 s)
BIN="${ROLLBASE_BIN:?set ROLLBASE_BIN}"
TESTS="${ROLLBASE_TESTS:-}"
W="${ROLLBASE_WORK:-/tmp/rollbase}"
AWKF="${ROLLBASE_CHECKS_AWK:?set ROLLBASE_CHECKS_AWK}"
IFACE=vcan0
# iproute2's ip, by path in the VM (busybox sh may prefer its own applet, which is enough for
# `link set up/down` but not for everything)
IP="${ROLLBASE_IP:-ip}"
mkdir -p "$W"
PATH="$BIN:$PATH"
export PATH

PASSED=0
RAN=0
FAILED=""
SUMMARY_FRAMES="-"
SUMMARY_SYNC="-"

now() { cut -d' ' -f1 /proc/uptime; }
T0=$(now)
elapsed() { awk -v a="$T0" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }
say() { echo "[checks $(elapsed)s] $*"; }
want() {
    [ -z "$ROLLBASE_CHECKS" ] && return 0
    case " $ROLLBASE_CHECKS " in *" $1 "*) return 0 ;; esac
    return 1
}
# key=value lookup in a file of key=value lines
kv() { sed -n "s/^$2=//p" "$1" | head -n 1; }
# a number field from a one-line JSON object
jnum() { sed -n "s/.*\"$2\":\([-0-9.eE+]*\).*/\1/p" "$1" | head -n 1; }
jstr() { sed -n "s/.*\"$2\":\"\([^\"]*\)\".*/\1/p" "$1" | head -n 1; }
# awk comparison helper: le A B -> true when A <= B (numbers)
le() { awk -v a="$1" -v b="$2" 'BEGIN { exit !(a != "" && a + 0 <= b + 0) }'; }
ms() { awk -v a="$1" 'BEGIN { printf "%.1f", a * 1000 }'; }

record() { # n name status detail
    RAN=$((RAN + 1))
    if [ "$3" = 0 ]; then
        PASSED=$((PASSED + 1))
        echo "CHECK $1: PASS $2${4:+ -- $4}"
    else
        FAILED="$FAILED $1"
        echo "CHECK $1: FAIL $2${4:+ -- $4}"
    fi
}

# Stops a background process and waits for it (ignores one that already exited).
stop_pid() { # pid [signal]
    [ -n "$1" ] || return 0
    kill "-${2:-INT}" "$1" 2>/dev/null
    i=0
    while kill -0 "$1" 2>/dev/null && [ $i -lt 50 ]; do sleep 0.1; i=$((i + 1)); done
    kill -KILL "$1" 2>/dev/null
    wait "$1" 2>/dev/null
    return 0
}

have() { [ -x "$BIN/$1" ] || command -v "$1" >/dev/null 2>&1; }

# CRC-8 SAE J1850 of "id byte..." (hex), printed as two hex digits.
crc8() {
    echo "$*" | awk -v f="$AWKF" '
        function bx(a, b,    r, p, i) { r = 0; p = 1; for (i = 0; i < 8; i++) { if ((a % 2) != (b % 2)) r += p; a = int(a / 2); b = int(b / 2); p *= 2 } return r }
        function hv(s,    i, v) { v = 0; s = toupper(s); for (i = 1; i <= length(s); i++) v = v * 16 + index("0123456789ABCDEF", substr(s, i, 1)) - 1; return v }
        { id = hv($1); c = 255; n = 0; B[n++] = id % 256; B[n++] = int(id / 256)
          for (i = 2; i <= NF; i++) B[n++] = hv($i)
          for (j = 0; j < n; j++) { c = bx(c, B[j]); for (k = 0; k < 8; k++) { if (c >= 128) c = bx((c * 2) % 256, 29); else c = (c * 2) % 256 } }
          printf "%02X\n", bx(c, 255) }'
}

# ---------------------------------------------------------------------------------------------
check0() {
    have candump && have cansend || { record 0 "kernel vcan0 + can-utils" 1 "candump/cansend missing"; return; }
    rm -f "$W/c0.log" "$W/c0b.log"
    timeout 10 candump -L -n 1 "$IFACE" >"$W/c0.log" 2>&1 &
    cp=$!
    sleep 0.5
    cansend "$IFACE" 123#DEADBEEF01
    wait $cp
    rc=$?
    got="$(cut -d' ' -f3 "$W/c0.log")"
    timeout 10 candump -L -n 100 "$IFACE" >"$W/c0b.log" 2>&1 &
    cp=$!
    sleep 0.5
    cangen "$IFACE" -n 100 -g 1 -I 7A0 -L 8
    wait $cp
    n=$(grep -c ' 7A0#' "$W/c0b.log")
    if [ $rc = 0 ] && [ "$got" = "123#DEADBEEF01" ] && [ "$n" = 100 ]; then
        record 0 "kernel vcan0 + can-utils" 0 "cansend->candump round trip 123#DEADBEEF01, cangen 100/100 frames"
    else
        record 0 "kernel vcan0 + can-utils" 1 "candump rc $rc got '$got', cangen frames seen $n/100"
    fi
}

# ---------------------------------------------------------------------------------------------
check1() {
    st=0
    detail=""
    found=0
    for t in "$TESTS"/*; do
        [ -x "$t" ] || continue
        found=1
        name=$(basename "$t")
        say "check 1: running $name on $IFACE"
        timeout 180 "$t" --test-threads=1 --nocapture >"$W/c1-$name.log" 2>&1
        rc=$?
        sed 's/^/    | /' "$W/c1-$name.log"
        ntests=$(sed -n 's/^test result: .* \([0-9]*\) passed.*/\1/p' "$W/c1-$name.log" | head -n 1)
        if [ $rc != 0 ]; then st=1; detail="$detail $name: exit $rc;"
        elif grep -q 'skipped: vcan0' "$W/c1-$name.log"; then st=1; detail="$detail $name: tests skipped vcan0;"
        else detail="$detail $name: ${ntests:-?} passed;"
        fi
        "$IP" link set up "$IFACE" 2>/dev/null
    done
    [ $found = 1 ] || { st=1; detail="$detail no SocketCAN test binary packed;"; }

    # Bus-down reporting by a live receiver (the SocketCAN backend's recv path).
    if have rollbase; then
        rollbase monitor --bus "$IFACE" >"$W/c1-mon.out" 2>"$W/c1-mon.err" &
        mp=$!
        sleep 1
        cansend "$IFACE" 080#00000000
        sleep 0.3
        "$IP" link set "$IFACE" down
        i=0
        while kill -0 $mp 2>/dev/null && [ $i -lt 50 ]; do sleep 0.1; i=$((i + 1)); done
        if kill -0 $mp 2>/dev/null; then
            stop_pid $mp INT
            st=1; detail="$detail monitor kept running after vcan0 went down;"
        else
            wait $mp
            mrc=$?
            msg=$(grep -m1 'error' "$W/c1-mon.err")
            if [ $mrc != 0 ] && grep -q 'down' "$W/c1-mon.err"; then
                detail="$detail monitor: exit $mrc '$msg';"
            else
                st=1; detail="$detail monitor on vcan0 down: exit $mrc '$(head -c 200 "$W/c1-mon.err")';"
            fi
        fi
        "$IP" link set up "$IFACE"
    else
        st=1; detail="$detail rollbase missing;"
    fi

    # Bus-down mid-run: the controller must report the bus error and end in Fault (not hang,
    # not claim Stopped).
    if have rollbase && have rollbase-sim; then
        rollbase-sim --bus "$IFACE" --start scenario:seed000 >"$W/c1-sim.out" 2>"$W/c1-sim.err" &
        sp=$!
        sleep 1
        rollbase run --bus "$IFACE" --trajectory scenario:seed000 --duration 20 --json >"$W/c1-run.json" 2>"$W/c1-run.err" &
        rp=$!
        sleep 4
        "$IP" link set "$IFACE" down
        i=0
        while kill -0 $rp 2>/dev/null && [ $i -lt 100 ]; do sleep 0.1; i=$((i + 1)); done
        if kill -0 $rp 2>/dev/null; then
            stop_pid $rp KILL
            st=1; detail="$detail run did not end within 10 s of vcan0 going down;"
        else
            wait $rp
            rrc=$?
            fs=$(jstr "$W/c1-run.json" supervisor_final_state)
            fr=$(sed -n 's/.*"fault_reason":\("[^"]*"\|null\).*/\1/p' "$W/c1-run.json")
            sed 's/^/    run| /' "$W/c1-run.err" "$W/c1-run.json" | tail -n 8
            if [ $rrc != 0 ] && [ "$fs" = fault ]; then
                detail="$detail run: exit $rrc, final state $fs, reason $fr;"
            else
                st=1; detail="$detail run on vcan0 down: exit $rrc, final state '${fs}' reason ${fr} $(tail -n 3 "$W/c1-run.err" | tr '\n' ' ');"
            fi
        fi
        "$IP" link set up "$IFACE"
        stop_pid $sp INT
    else
        st=1; detail="$detail rollbase-sim missing (bus-down mid-run not run);"
    fi
    record 1 "driver SocketCAN tests + bus-down reporting" $st "$detail"
}

# ---------------------------------------------------------------------------------------------
# Checks 2, 3 and 4 share one run: sim + controller + candump on vcan0, one bad SETPOINT injected.
C2_DONE=0
run_stack() {
    C2_DONE=1
    C2_OK=0
    rm -f "$W/c2-cap.log"
    if ! have rollbase || ! have rollbase-sim; then
        C2_ERR="rollbase or rollbase-sim missing"
        return
    fi
    candump -L "$IFACE" >"$W/c2-cap.log" 2>"$W/c2-candump.err" &
    cp=$!
    rollbase-sim --bus "$IFACE" --start scenario:seed000 >"$W/c2-sim.out" 2>"$W/c2-sim.err" &
    sp=$!
    sleep 1
    dur=""
    [ -n "$ROLLBASE_DURATION" ] && dur="--duration $ROLLBASE_DURATION"
    say "check 2: rollbase run --bus $IFACE --trajectory scenario:seed000 $dur"
    # shellcheck disable=SC2086
    rollbase run --bus "$IFACE" --trajectory scenario:seed000 $dur --json \
        --candump "$W/c2-ctl.log" >"$W/c2-run.json" 2>"$W/c2-run.err" &
    rp=$!
    # Check 4: at 8 s (alignment is over, the platform tracks), one SETPOINT for node 1 asking
    # 20 rad/s with enable set and a CRC that is deliberately wrong.
    sleep 8
    good=$(crc8 201 20 4E 00 00 01)
    bad=$(printf '%02X' $(( (0x$good + 0x5A) % 256 )))
    C4_FRAME="201#204E000001$bad"
    if kill -0 $rp 2>/dev/null; then
        cansend "$IFACE" "$C4_FRAME"
        say "check 4: injected $C4_FRAME (correct CRC would be $good)"
        C4_SENT=1
    else
        C4_SENT=0
    fi
    wait $rp
    C2_RC=$?
    sleep 0.3
    stop_pid $sp INT
    stop_pid $cp TERM
    sed 's/^/    run| /' "$W/c2-run.err" "$W/c2-run.json" | tail -n 20
    sed 's/^/    sim| /' "$W/c2-sim.out" "$W/c2-sim.err" | tail -n 30
    awk -v skip="${C4_FRAME:-}" -f "$AWKF" "$W/c2-cap.log" >"$W/c2-stats.txt"
    sed 's/^/    capture| /' "$W/c2-stats.txt"
    C2_OK=1
}

check2() {
    [ $C2_DONE = 1 ] || run_stack
    [ $C2_OK = 1 ] || { record 2 "full stack on vcan0 (seed000)" 1 "$C2_ERR"; return; }
    j="$W/c2-run.json"
    fs=$(jstr "$j" supervisor_final_state)
    pe=$(jnum "$j" max_position_error_m)
    he=$(jnum "$j" max_heading_error_rad)
    le_=$(jnum "$j" max_leg_error_m)
    cy=$(jnum "$j" cycles)
    dm=$(jnum "$j" deadline_misses)
    ea=$(jstr "$j" errors_against)
    d="exit $C2_RC, final $fs, $cy cycles, $dm deadline misses, errors vs $ea: pos $(ms "$pe") mm, heading $(awk -v h="$he" 'BEGIN { printf "%.3f", h * 57.29577951 }') deg, legs $(ms "$le_") mm"
    st=0
    [ "$C2_RC" = 0 ] && [ "$fs" = stopped ] || st=1
    le "$pe" 0.005 || st=1
    le "$he" 0.00872664626 || st=1
    le "$le_" 0.002 || st=1
    record 2 "full stack on vcan0 (seed000)" $st "$d"
}

# rollbase monitor --candump --summary over check 2's capture, once (checks 3 and 4 read it;
# a re-run of check 4 alone decodes it too). MON_RC: the monitor's exit status.
MON_DONE=0
monitor_capture() {
    [ $MON_DONE = 1 ] && return
    MON_DONE=1
    rollbase monitor --candump "$W/c2-cap.log" --summary >"$W/c3-mon.txt" 2>"$W/c3-mon.err"
    MON_RC=$?
}

check3() {
    [ $C2_DONE = 1 ] || run_stack
    [ $C2_OK = 1 ] || { record 3 "capture decoded" 1 "$C2_ERR"; return; }
    s="$W/c2-stats.txt"
    st=0
    d=""
    want_bad=0
    mframes=""
    [ "${C4_SENT:-0}" = 1 ] && want_bad=1
    # rollbase monitor --candump --summary over the same capture. Its last line is the summary:
    # "frames: N, accepted: SYNC a ...; rejected: R (bad CRC c, wrong DLC d, unknown id u, out of
    # range o, repeated r, skipped s with l lost, other x); unparsable lines: p".
    monitor_capture
    if [ "$MON_RC" = 0 ]; then
        msum=$(grep '^frames: ' "$W/c3-mon.txt" | tail -n 1)
        say "check 3: rollbase monitor: $msum"
        grep 'REJECTED' "$W/c3-mon.txt" | head -n 5 | sed 's/^/    monitor| /'
        mframes=$(echo "$msum" | sed -n 's/^frames: \([0-9]*\),.*/\1/p')
        mrej=$(echo "$msum" | sed -n 's/.*; rejected: \([0-9]*\) (.*/\1/p')
        mcrc=$(echo "$msum" | sed -n 's/.*(bad CRC \([0-9]*\),.*/\1/p')
        munp=$(echo "$msum" | sed -n 's/.*unparsable lines: \([0-9]*\).*/\1/p')
        if [ -z "$msum" ]; then
            st=1; d="monitor printed no summary line;"
        elif [ "$mrej" = "$want_bad" ] && [ "$mcrc" = "$want_bad" ] && [ "$munp" = 0 ]; then
            d="monitor: $mframes frames, $mrej rejected (bad CRC $mcrc: the injected frame);"
        else
            st=1; d="monitor: $mframes frames, $mrej rejected, bad CRC $mcrc (expected $want_bad), $munp unparsable;"
        fi
    else
        st=1
        d="monitor failed: $(head -c 300 "$W/c3-mon.err");"
    fi
    frames=$(kv "$s" frames)
    skipped=$(kv "$s" skipped)
    bt=$(kv "$s" badctr)
    mean=$(kv "$s" sync_mean_ms)
    std=$(kv "$s" sync_std_ms)
    nodes=$(kv "$s" nodes)
    spc=$(kv "$s" setpoint_cycles)
    spbad=$(kv "$s" setpoint_bad_cycles)
    miss="$(kv "$s" missing_a)/$(kv "$s" missing_b)"
    extra="$(kv "$s" extra_a)/$(kv "$s" extra_b)"
    late="$(kv "$s" late_a)/$(kv "$s" late_b)"
    amax=$(kv "$s" answer_max_ms)
    SUMMARY_FRAMES="$((frames + skipped))"
    SUMMARY_SYNC="mean $mean ms, std $std ms, min $(kv "$s" sync_min_ms) ms, max $(kv "$s" sync_max_ms) ms over $(kv "$s" sync) SYNCs"
    # Everything the monitor decoded, the capture decoder saw too (it skips only the injected frame).
    [ -z "$mframes" ] || [ "$mframes" = "$((frames + skipped))" ] || { st=1; d="$d monitor saw $mframes frames, capture.awk $((frames + skipped));"; }
    [ "$bt" = 0 ] || { st=1; d="$d $bt counter errors;"; }
    awk -v m="$mean" 'BEGIN { exit !(m != "" && m >= 3.96 && m <= 4.04) }' || { st=1; d="$d SYNC mean $mean ms not within 1 % of 4 ms;"; }
    [ "$nodes" = 4 ] || { st=1; d="$d $nodes nodes answered SYNCs (expected 4);"; }
    [ "${spc:-0}" -gt 0 ] && [ "$spbad" = 0 ] || { st=1; d="$d $spbad of $spc cycles without exactly one SETPOINT per node;"; }
    [ "$miss" = 0/0 ] && [ "$extra" = 0/0 ] || { st=1; d="$d SYNC answers FEEDBACK_A/FEEDBACK_B missing $miss, extra $extra;"; }
    record 3 "capture decoded (CRC, counters, SYNC period, frames per cycle)" $st \
        "$d $((frames + skipped)) frames; SYNC $SUMMARY_SYNC; $nodes nodes answered every SYNC with one FEEDBACK_A and one FEEDBACK_B (missing $miss, extra $extra, after the next SYNC $late, longest answer $amax ms); $spc cycles with one SETPOINT per node (bad $spbad); counter errors $bt"
}

check4() {
    [ $C2_DONE = 1 ] || run_stack
    [ $C2_OK = 1 ] || { record 4 "bad-CRC SETPOINT rejected" 1 "$C2_ERR"; return; }
    st=0
    d=""
    [ "${C4_SENT:-0}" = 1 ] || { record 4 "bad-CRC SETPOINT rejected" 1 "the run ended before the injection"; return; }
    # In the capture exactly once; rollbase monitor rejected it for its CRC (check 3 verifies the
    # monitor's totals: exactly one rejection, a bad CRC).
    n=$(grep -c " $C4_FRAME\$" "$W/c2-cap.log")
    monitor_capture
    [ "$n" = 1 ] || { st=1; d="$d frame seen $n times in the capture;"; }
    grep -q "REJECTED: SETPOINT (id 0x201) CRC" "$W/c3-mon.txt" 2>/dev/null \
        && d="$d monitor: rejected for its CRC;" || { st=1; d="$d rollbase monitor did not reject it for its CRC;"; }
    # The simulator counted it: on exit it prints one line per module,
    # "  node N: STATE, S SYNCs answered, A setpoints ok, C bad CRC, K bad counter, W watchdog trips".
    simcrc=$(sed -n 's/^ *node \([0-9]*\): .*, \([0-9]*\) bad CRC, .*/\1:\2/p' "$W/c2-sim.err" | tr '\n' ' ')
    case " $simcrc" in
        *" 1:1 "*)
            others=$(echo "$simcrc" | tr ' ' '\n' | grep -v '^1:' | grep -v -e '^$' | grep -vc ':0$')
            if [ "$others" = 0 ]; then d="$d simulator counted it (bad CRC per node $simcrc);"
            else st=1; d="$d other nodes counted bad CRCs ($simcrc);"; fi ;;
        *) st=1; d="$d simulator did not count 1 bad CRC for node 1 (per node: '${simcrc}');" ;;
    esac
    # Every genuine SETPOINT to node 1 was still accepted: "A setpoints ok" == SYNCs in the capture.
    sp1=$(sed -n 's/^ *node 1: .*, \([0-9]*\) setpoints ok, .*/\1/p' "$W/c2-sim.err")
    nsync=$(kv "$W/c2-stats.txt" sync)
    [ "$sp1" = "$nsync" ] || { st=1; d="$d node 1 accepted $sp1 SETPOINTs for $nsync SYNCs;"; }
    # Not disturbed: no module left `enabled` for a fault during the run, the run passed check 2's bounds.
    faults=$(kv "$W/c2-stats.txt" fault_during_run)
    [ "$faults" = 0 ] || { st=1; d="$d $faults modules reported a fault while the controller ran;"; }
    fs=$(jstr "$W/c2-run.json" supervisor_final_state)
    pe=$(jnum "$W/c2-run.json" max_position_error_m)
    [ "$C2_RC" = 0 ] && [ "$fs" = stopped ] && le "$pe" 0.005 || { st=1; d="$d run disturbed (exit $C2_RC, $fs, pos err $pe m);"; }
    record 4 "bad-CRC SETPOINT rejected" $st "injected $C4_FRAME;$d run ended $fs"
}

# ---------------------------------------------------------------------------------------------
check5() {
    if ! have rollbase || ! have rollbase-sim; then
        record 5 "controller killed -> modules stop" 1 "rollbase or rollbase-sim missing"
        return
    fi
    candump -L "$IFACE" >"$W/c5-cap.log" 2>/dev/null &
    cp=$!
    rollbase-sim --bus "$IFACE" --start scenario:seed000 >"$W/c5-sim.out" 2>"$W/c5-sim.err" &
    sp=$!
    sleep 1
    rollbase run --bus "$IFACE" --trajectory scenario:seed000 --json >"$W/c5-run.json" 2>"$W/c5-run.err" &
    rp=$!
    # 6 s in: aligned and accelerating along the trajectory.
    sleep 6
    alive=0
    kill -0 $rp 2>/dev/null && alive=1
    kill -KILL $rp 2>/dev/null
    wait $rp 2>/dev/null
    say "check 5: controller (pid $rp) killed with SIGKILL"
    sleep 1
    stop_pid $sp INT
    stop_pid $cp TERM
    awk -f "$AWKF" "$W/c5-cap.log" >"$W/c5-kill.txt"
    grep '^stop_node\|^worst\|^moving\|^last_setpoint\|^frames\|^nodes' "$W/c5-kill.txt" | sed 's/^/    kill| /'
    st=0
    d=""
    [ $alive = 1 ] || { st=1; d="$d controller had already exited before the kill;"; }
    nodes=$(kv "$W/c5-kill.txt" nodes)
    moving=$(kv "$W/c5-kill.txt" moving_nodes)
    worst=$(kv "$W/c5-kill.txt" worst_stop_ms)
    [ "$nodes" = 4 ] || { st=1; d="$d $nodes nodes seen;"; }
    [ "${moving:-0}" -gt 0 ] || { st=1; d="$d no wheel was turning when the controller died;"; }
    # The last SETPOINT each module got must still have enabled it: a module that the controller
    # itself disabled before dying proves nothing about the watchdog.
    [ "$(kv "$W/c5-kill.txt" last_setpoint_disabled)" = 0 ] || { st=1; d="$d the controller had disabled modules before it died;"; }
    # The watchdog runs from the last valid SETPOINT; the controller's death is noticed at the
    # first missing one, one 4 ms cycle later: stopped within 50 ms of that = 54 ms after the last.
    le "$worst" 54 || { st=1; d="$d slowest module stopped $worst ms after its last SETPOINT (> 4 + 50 ms);"; }
    simwd=$(sed -n 's/^ *node \([0-9]*\): \([A-Za-z]*\), .*, \([0-9]*\) watchdog trips.*/\1:\2:\3/p' "$W/c5-sim.err" | tr '\n' ' ')
    ntrip=$(echo "$simwd" | tr ' ' '\n' | grep -c ':[1-9][0-9]*$')
    [ "$ntrip" = "$nodes" ] || { st=1; d="$d simulator reports watchdog trips on $ntrip of $nodes modules ($simwd);"; }
    record 5 "controller killed -> modules stop" $st "$d $nodes modules, $moving turning at the kill, simulator node:state:watchdog trips $simwd, slowest stopped $worst ms after its last SETPOINT (<= 54 ms: 50 ms after the first missing one)"
}

# ---------------------------------------------------------------------------------------------
# Per node, the first EMCY for a lost master (0x8250 / 0x8130) after the controller's last
# RPDO1, and whether a statusword in fault followed; candump -L lines on stdin.
cia402_kill_stats() {
    awk '
        function hv(s,    i, v) { v = 0; s = toupper(s); for (i = 1; i <= length(s); i++) v = v * 16 + index("0123456789ABCDEF", substr(s, i, 1)) - 1; return v }
        {
            t = substr($1, 2, length($1) - 2) + 0
            split($3, a, "#"); id = hv(a[1]); d = a[2]
            if (id >= 513 && id <= 520) last_rpdo = t
            if (id >= 129 && id <= 136 && last_rpdo != "") {
                c = substr(d, 1, 4)
                if ((c == "5082" || c == "3081") && !((id - 128) in em)) em[id - 128] = t
            }
            if (id >= 641 && id <= 648 && length(d) == 4) {
                sw = hv(substr(d, 3, 2) substr(d, 1, 2))
                if (sw % 16 == 8 || sw % 16 == 15) flt[id - 640] = 1
            }
        }
        END {
            worst = 0; n = 0; nf = 0
            for (k in em) { n++; dt = (em[k] - last_rpdo) * 1000; if (dt > worst) worst = dt }
            for (k in flt) nf++
            printf "emcy_nodes=%d\nworst_emcy_ms=%.1f\nfault_nodes=%d\n", n, worst, nf
        }'
}

# Starts `candump -L` into $W/PREFIX-cap.log and the simulated CiA 402/406 devices (output in
# $W/PREFIX-sim.*) at the seed-000 start; sets cp and sp to their pids; gives them 1 s.
start_cia402_sim() {
    candump -L "$IFACE" >"$W/$1-cap.log" 2>/dev/null &
    cp=$!
    rollbase-sim --bus "$IFACE" --profile cia402 --start scenario:seed000 >"$W/$1-sim.out" 2>"$W/$1-sim.err" &
    sp=$!
    sleep 1
}

check6() {
    if ! have rollbase || ! have rollbase-sim; then
        record 6 "CiA 402 profile on vcan0 (seed000)" 1 "rollbase or rollbase-sim missing"
        return
    fi
    start_cia402_sim c6
    dur=""
    [ -n "$ROLLBASE_DURATION" ] && dur="--duration $ROLLBASE_DURATION"
    say "check 6: rollbase run --bus $IFACE --profile cia402 --trajectory scenario:seed000 $dur"
    # shellcheck disable=SC2086
    rollbase run --bus "$IFACE" --profile cia402 --trajectory scenario:seed000 $dur --json \
        >"$W/c6-run.json" 2>"$W/c6-run.err"
    rc=$?
    sleep 0.3
    stop_pid $sp INT
    stop_pid $cp TERM
    sed 's/^/    run| /' "$W/c6-run.err" "$W/c6-run.json" | tail -n 12
    sed 's/^/    sim| /' "$W/c6-sim.out" "$W/c6-sim.err" | tail -n 20
    j="$W/c6-run.json"
    fs=$(jstr "$j" supervisor_final_state)
    pe=$(jnum "$j" max_position_error_m)
    he=$(jnum "$j" max_heading_error_rad)
    le_=$(jnum "$j" max_leg_error_m)
    cy=$(jnum "$j" cycles)
    st=0
    d="exit $rc, final $fs, $cy cycles: pos $(ms "$pe") mm, heading $(awk -v h="$he" 'BEGIN { printf "%.3f", h * 57.29577951 }') deg, legs $(ms "$le_") mm;"
    [ "$rc" = 0 ] && [ "$fs" = stopped ] || st=1
    le "$pe" 0.005 || st=1
    le "$he" 0.00872664626 || st=1
    le "$le_" 0.002 || st=1
    cap="$W/c6-cap.log"
    boot=$(grep -E ' 70[1-9A-C]#00$' "$cap" | awk '{ split($3, a, "#"); print a[1] }' | sort -u | grep -c .)
    starts=$(grep -E ' 000#01(0[1-9A-C])$' "$cap" | sort -u -k3 | grep -c .)
    # The simulator's devices are real drives' twins (issue 24): some device types lack an
    # object the boot plan writes as an optional step (0x6091 on the rolling drives, TPDO3/4 on
    # the encoders), answered "object does not exist" (abort code 0x06020000, bytes 00 00 02 06),
    # and every device sends an informational EMCY (error register 0, vendor code 0xFF01) when
    # started. Those are expected; any other abort, or an EMCY with an error register set (a
    # fault), fails the check.
    aborts=$(grep -cE ' 58[1-9A-C]#80' "$cap")
    bad_aborts=$(grep -E ' 58[1-9A-C]#80' "$cap" | grep -vc '00000206$')
    emcy_info=$(grep -E ' 08[1-9A-C]#' "$cap" | awk '{ split($3, a, "#"); if (substr(a[2], 1, 4) != "0000" && substr(a[2], 5, 2) == "00") n++ } END { print n + 0 }')
    emcy_fault=$(grep -E ' 08[1-9A-C]#' "$cap" | awk '{ split($3, a, "#"); if (substr(a[2], 1, 4) != "0000" && substr(a[2], 5, 2) != "00") n++ } END { print n + 0 }')
    d="$d capture: $(grep -c . "$cap") frames, boot-ups from $boot nodes, NMT start to $starts nodes, $aborts SDO aborts ($bad_aborts other than 'object does not exist'), EMCY: $emcy_info informational, $emcy_fault fault;"
    [ "$boot" = 12 ] && [ "$starts" = 12 ] && [ "$bad_aborts" = 0 ] && [ "$emcy_fault" = 0 ] || st=1
    if rollbase monitor --profile cia402 --candump "$cap" --summary >"$W/c6-mon.txt" 2>"$W/c6-mon.err"; then
        msum=$(tail -n 1 "$W/c6-mon.txt")
        grep 'REJECTED' "$W/c6-mon.txt" | head -n 5 | sed 's/^/    monitor| /'
        rej=$(echo "$msum" | sed -n 's/.*rejected: \([0-9]*\);.*/\1/p')
        d="$d monitor: $msum"
        [ "$rej" = 0 ] || st=1
    else
        st=1; d="$d monitor failed: $(head -c 200 "$W/c6-mon.err")"
    fi
    record 6 "CiA 402 profile on vcan0 (seed000)" $st "$d"
}

check7() {
    if ! have rollbase || ! have rollbase-sim; then
        record 7 "CiA 402: controller killed -> drives fault" 1 "rollbase or rollbase-sim missing"
        return
    fi
    start_cia402_sim c7
    rollbase run --bus "$IFACE" --profile cia402 --trajectory scenario:seed000 --json >"$W/c7-run.json" 2>"$W/c7-run.err" &
    rp=$!
    sleep 6
    alive=0
    kill -0 $rp 2>/dev/null && alive=1
    kill -KILL $rp 2>/dev/null
    wait $rp 2>/dev/null
    say "check 7: controller (pid $rp) killed with SIGKILL"
    sleep 1
    stop_pid $sp INT
    stop_pid $cp TERM
    cia402_kill_stats <"$W/c7-cap.log" >"$W/c7-kill.txt"
    sed 's/^/    kill| /' "$W/c7-kill.txt"
    sed 's/^/    run| /' "$W/c7-run.err" "$W/c7-run.json" | tail -n 12
    sed 's/^/    sim| /' "$W/c7-sim.err" | tail -n 16
    en=$(kv "$W/c7-kill.txt" emcy_nodes)
    worst=$(kv "$W/c7-kill.txt" worst_emcy_ms)
    fn=$(kv "$W/c7-kill.txt" fault_nodes)
    st=0
    d=""
    [ $alive = 1 ] || { st=1; d="$d controller had already exited before the kill;"; }
    [ "$en" = 8 ] || { st=1; d="$d EMCY for the lost master from $en of 8 drives;"; }
    le "$worst" 70 || { st=1; d="$d slowest EMCY $worst ms after the last RPDO (> 70 ms);"; }
    [ "$fn" = 8 ] || { st=1; d="$d statusword in fault from $fn of 8 drives;"; }
    record 7 "CiA 402: controller killed -> drives fault" $st "$d EMCY from $en drives, slowest $worst ms after the last RPDO (RPDO deadline 50 ms, heartbeat 60 ms); $fn drives in fault"
}

# ---------------------------------------------------------------------------------------------
# Check 8: two buses on the kernel's SocketCAN (issue 25). The six-wheel example (wheels 1-3 on
# bus 0, 4-6 on bus 1) with vcan0 and vcan1: rollbase-sim and rollbase run take one --bus each,
# candump listens on both. Each bus carries one SYNC per cycle and only its own wheels' frames;
# then vcan1 goes down mid-run and the whole base must stop: the run ends within 10 s in Fault
# (not Stopped, not hanging), and vcan0's SYNCs end with it.
IF2=vcan1
check8() {
    name="two buses on vcan0 + vcan1 (six-wheel)"
    "$IP" link show "$IF2" >/dev/null 2>&1 || "$IP" link add dev "$IF2" type vcan 2>/dev/null
    "$IP" link set up "$IF2" 2>/dev/null
    if ! "$IP" link show "$IF2" 2>/dev/null | grep -q '[<,]UP[,>]'; then
        record 8 "$name" 1 "no usable $IF2: create it (sudo ip link add dev $IF2 type vcan && sudo ip link set up $IF2)"
        return
    fi
    if ! have rollbase || ! have rollbase-sim; then
        record 8 "$name" 1 "rollbase or rollbase-sim missing"
        return
    fi
    rollbase config default --example six-wheel >"$W/six.toml" 2>"$W/c8-cfg.err" || {
        record 8 "$name" 1 "config default --example six-wheel: $(head -c 200 "$W/c8-cfg.err")"
        return
    }
    # One candump per interface: candump ends when an interface it reads goes down.
    candump -L "$IFACE" >"$W/c8-cap0.log" 2>"$W/c8-candump0.err" &
    c0=$!
    candump -L "$IF2" >"$W/c8-cap1.log" 2>"$W/c8-candump1.err" &
    c1=$!
    rollbase-sim --config "$W/six.toml" --bus "$IFACE" --bus "$IF2" --start scenario:seed000 \
        >"$W/c8-sim.out" 2>"$W/c8-sim.err" &
    sp=$!
    sleep 1
    say "check 8: rollbase run --config six-wheel --bus $IFACE --bus $IF2 --trajectory scenario:seed000; $IF2 down once both buses carried 1100 SYNCs (at most 20 s)"
    rollbase run --config "$W/six.toml" --bus "$IFACE" --bus "$IF2" --trajectory scenario:seed000 \
        --duration 30 --json >"$W/c8-run.json" 2>"$W/c8-run.err" &
    rp=$!
    # vcan1 goes down mid-run: after 1100 SYNCs on each bus (4.4 s of cycles), not after a
    # fixed time — the emulated guest may take seconds longer to start the run when the host
    # is busy, and a fixed 6 s then left fewer than the 1000 SYNCs asked below.
    i=0
    while [ $i -lt 100 ]; do
        a=$(grep -c ' 080#' "$W/c8-cap0.log" 2>/dev/null)
        b=$(grep -c ' 080#' "$W/c8-cap1.log" 2>/dev/null)
        [ "${a:-0}" -ge 1100 ] && [ "${b:-0}" -ge 1100 ] && break
        kill -0 $rp 2>/dev/null || break
        sleep 0.2
        i=$((i + 1))
    done
    alive=0
    kill -0 $rp 2>/dev/null && alive=1
    "$IP" link set "$IF2" down
    i=0
    while kill -0 $rp 2>/dev/null && [ $i -lt 100 ]; do sleep 0.1; i=$((i + 1)); done
    st=0
    d=""
    if kill -0 $rp 2>/dev/null; then
        stop_pid $rp KILL
        st=1; d="$d run did not end within 10 s of $IF2 going down;"
        rrc=""
    else
        wait $rp
        rrc=$?
    fi
    sleep 0.3
    "$IP" link set up "$IF2"
    stop_pid $sp INT
    stop_pid $c0 TERM
    stop_pid $c1 TERM
    sed 's/^/    run| /' "$W/c8-run.err" "$W/c8-run.json" | tail -n 10
    sed 's/^/    sim| /' "$W/c8-sim.out" "$W/c8-sim.err" | tail -n 8
    fs=$(jstr "$W/c8-run.json" supervisor_final_state)
    fr=$(sed -n 's/.*"fault_reason":\("[^"]*"\|null\).*/\1/p' "$W/c8-run.json")
    cy=$(jnum "$W/c8-run.json" cycles)
    # Per capture: SYNCs (id 080), frames of a node that is not on this bus (node = id & 0x7F,
    # wheels 1-3 on bus 0 and 4-6 on bus 1), and the time of the last SYNC.
    stats() { # file bus
        awk -v bus="$2" '
            function hv(s,    i, v) { v = 0; s = toupper(s); for (i = 1; i <= length(s); i++) v = v * 16 + index("0123456789ABCDEF", substr(s, i, 1)) - 1; return v }
            { split($3, f, "#"); id = hv(f[1]); node = id % 128
              if (id == 128) { syncs++; t = substr($1, 2, length($1) - 2) + 0; if (!first) first = t; last = t }
              else if (node >= 1 && node <= 6 && int((node - 1) / 3) != bus) wrong++ }
            END { printf "syncs=%d wrong=%d span=%.2f\n", syncs, wrong, last - first }' "$1"
    }
    s0=$(stats "$W/c8-cap0.log" 0)
    s1=$(stats "$W/c8-cap1.log" 1)
    say "check 8: $IFACE: $s0; $IF2: $s1"
    n0=$(echo "$s0" | sed -n 's/.*syncs=\([0-9]*\).*/\1/p')
    n1=$(echo "$s1" | sed -n 's/.*syncs=\([0-9]*\).*/\1/p')
    w0=$(echo "$s0" | sed -n 's/.*wrong=\([0-9]*\).*/\1/p')
    w1=$(echo "$s1" | sed -n 's/.*wrong=\([0-9]*\).*/\1/p')
    sp0=$(echo "$s0" | sed -n 's/.*span=\([0-9.]*\).*/\1/p')
    [ $alive = 1 ] || { st=1; d="$d the run had already ended before $IF2 went down;"; }
    [ -n "$rrc" ] && [ "$rrc" != 0 ] && [ "$fs" = fault ] || { st=1; d="$d run: exit ${rrc:-none}, final state '$fs' (want a fault);"; }
    # At least 4 s of cycles on each bus before vcan1 went down (it goes down after 1100),
    # and vcan0's SYNCs ended within the 10 s the run had to stop.
    [ "${n0:-0}" -ge 1000 ] && [ "${n1:-0}" -ge 1000 ] || { st=1; d="$d SYNCs $n0 on $IFACE, $n1 on $IF2 (want >= 1000 each);"; }
    [ "${w0:-1}" = 0 ] && [ "${w1:-1}" = 0 ] || { st=1; d="$d frames on the wrong bus: $w0 on $IFACE, $w1 on $IF2;"; }
    le "${sp0:-99}" 16 || { st=1; d="$d SYNCs on $IFACE went on for $sp0 s (the run should end within 10 s of the loss);"; }
    record 8 "$name" $st "$d run: exit $rrc, final $fs after $cy cycles, reason $fr; $IFACE $s0; $IF2 $s1"
}

# ---------------------------------------------------------------------------------------------
say "rollbase vcan checks on $IFACE (work dir $W)"
for n in 0 1 2 3 4 5 6 7 8; do
    if want $n; then
        say "check $n ..."
        "check$n"
        "$IP" link set up "$IFACE" 2>/dev/null
    fi
done
say "summary: $PASSED/$RAN checks passed${FAILED:+ (failed:$FAILED)}; frames captured in the seed-000 run: $SUMMARY_FRAMES; SYNC period: $SUMMARY_SYNC"
if [ $RAN -gt 0 ] && [ $PASSED = $RAN ]; then
    echo "VCAN-VM-RESULT: pass $PASSED/$RAN"
else
    echo "VCAN-VM-RESULT: fail $PASSED/$RAN (failed:$FAILED)"
fi
