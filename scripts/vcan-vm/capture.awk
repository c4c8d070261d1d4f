# Decoder of a `candump -L` capture of the rollbase native protocol (docs/protocol.md) for
# scripts/vcan-vm/checks.sh: the timing and accounting that `rollbase monitor --candump` does not
# do. Frame integrity (CRC-8, DLC, ranges) is `rollbase monitor`'s job; this script only skips
# the frame given as -v skip=ID#DATA (the frame check 4 injects). Portable awk (busybox awk,
# mawk, gawk): no bit operations, no math library, no strtonum.
#
#   awk -v skip=201#... -f capture.awk capture.log     prints `key=value` lines:
#
# - frames, per-kind counts, rolling-counter errors (4-bit counter +1 mod 16 per id);
# - the SYNC period: mean, std, min, max (ms);
# - SYNC answers: a module answers every SYNC with one FEEDBACK_A and one FEEDBACK_B. The n-th
#   answer of a node belongs to the n-th SYNC of the capture: the checks start the simulator
#   (boot time 0) and the capture before the controller, so no SYNC finds a module in Boot. (Not
#   the n-th SYNC since the node's first answer: under emulation the first answers can come
#   several SYNCs late, and that alignment then counted them as answers without a SYNC.)
#   `missing_*` counts SYNCs never answered, `extra_*` answers without a SYNC,
#   `late_*` answers that came after the next SYNC, `answer_max_ms` the longest SYNC->answer time;
# - SETPOINTs: exactly one per node between one SYNC and the next (`setpoint_bad_cycles` counts
#   the cycles where that does not hold; the cycle cut short by the end of the capture is not
#   counted);
# - controller loss: per node, the last SETPOINT, whether it still had `enable` set, the wheel
#   speed fed back just before it, and the first frame after it showing the motors stopped
#   (STATUS state != enabled, or FEEDBACK_A with wheel_speed 0): `stop_node<n>=` lines and
#   `worst_stop_ms`; `fault_during_run` counts modules whose STATUS reported `fault` before the
#   controller's last SETPOINT to them.

function bxor(a, b,    r, p, i) {
    r = 0; p = 1
    for (i = 0; i < 8; i++) {
        if ((a % 2) != (b % 2)) r += p
        a = int(a / 2); b = int(b / 2); p *= 2
    }
    return r
}
function hexval(s,    i, v) {
    v = 0
    s = toupper(s)
    for (i = 1; i <= length(s); i++) v = v * 16 + index("0123456789ABCDEF", substr(s, i, 1)) - 1
    return v
}
function byte(i) { return HX[substr(hex, 2 * i + 1, 2)] }
function i16(lo, hi,    v) {
    v = hi * 256 + lo
    return (v >= 32768) ? v - 65536 : v
}
# square root by Newton's method (busybox awk may be built without math functions)
function root(x,    r, i) {
    if (x <= 0) return 0
    r = (x > 1) ? x : 1
    for (i = 0; i < 200; i++) r = (r + x / r) / 2
    return r
}
function new_node(n) {
    if (n in NODES) return
    NODES[n] = 1
    PA[n] = nsync; PB[n] = nsync   # every SYNC so far is owed an answer (see the header)
}
function answer(n, which,    pend, lat) {
    pend = (which == "A") ? PA[n] : PB[n]
    if (pend < 1) { EXTRA[which]++; return }
    lat = (t - SY[nsync - pend + 1]) * 1000
    if (lat > answer_max) answer_max = lat
    if (pend > 1) LATE[which]++
    if (which == "A") PA[n]--; else PB[n]--
}
BEGIN {
    for (i = 0; i < 256; i++) {
        h = sprintf("%02X", i); HX[h] = i; HX[tolower(h)] = i
        HX[substr(h, 1, 1) tolower(substr(h, 2, 1))] = i; HX[tolower(substr(h, 1, 1)) substr(h, 2, 1)] = i
    }
    frames = 0; unparsed = 0; other = 0; skipped = 0; badctr = 0
    nsync = 0; sum = 0; sumsq = 0; dmin = 1e9; dmax = 0
    sp_cycles = 0; sp_bad = 0; answer_max = 0
}
{
    # (1700000000.123456) vcan0 181#0011223344556677
    if (NF < 3 || substr($1, 1, 1) != "(") { unparsed++; next }
    if (skip != "" && toupper($3) == toupper(skip)) { skipped++; next }
    t = substr($1, 2, length($1) - 2) + 0
    p = index($3, "#")
    if (p == 0) { unparsed++; next }
    hex = substr($3, p + 1)
    if (substr(hex, 1, 1) == "R" || substr(hex, 1, 1) == "#") { other++; next }
    frames++
    id = hexval(substr($3, 1, p - 1))
    if (id == 128) k = "SYNC"
    else if (id > 512 && id < 528) k = "SETPOINT"
    else if (id > 384 && id < 400) k = "FEEDBACK_A"
    else if (id > 640 && id < 656) k = "FEEDBACK_B"
    else if (id > 1792 && id < 1808) k = "STATUS"
    else { other++; next }
    COUNT[k]++
    node = id % 16
    if (k == "SYNC") ctr = byte(2) % 16
    else if (k == "SETPOINT") ctr = int(byte(4) / 16)
    else if (k == "STATUS") ctr = int(byte(0) / 16)
    else ctr = byte(6) % 16
    if (id in LASTCTR) {
        if (ctr != (LASTCTR[id] + 1) % 16) {
            badctr++
            if (badctr <= 5) printf "badctr_frame=%s %s expected %d got %d\n", $1, $3, (LASTCTR[id] + 1) % 16, ctr
        }
    }
    LASTCTR[id] = ctr

    if (k == "SYNC") {
        if (nsync > 0) {
            d = (t - SY[nsync]) * 1000
            sum += d; sumsq += d * d
            if (d < dmin) dmin = d
            if (d > dmax) dmax = d
            # close the SETPOINT window of the previous cycle
            sp_cycles++
            bad = 0
            for (n in SPN) { if (WSP[n] != 1) bad = 1; WSP[n] = 0 }
            if (bad) {
                sp_bad++
                if (sp_bad <= 5) {
                    line = sprintf("setpoint_bad_cycle=sync@%.6f:", SY[nsync])
                    for (n in SPN) line = line " n" n
                    print line
                }
            }
        }
        nsync++
        SY[nsync] = t
        for (n in NODES) { PA[n]++; PB[n]++ }
    } else if (k == "SETPOINT") {
        SPN[node] = 1
        if (nsync > 0) WSP[node]++
        LAST_SP[node] = t
        LAST_EN[node] = byte(4) % 2
        SPEED_AT_LAST[node] = SPEED[node]
        STOP_T[node] = ""
    } else if (k == "FEEDBACK_A") {
        if (nsync > 0) { new_node(node); answer(node, "A") }
        ws = i16(byte(2), byte(3))
        SPEED[node] = ws
        if ((node in LAST_SP) && STOP_T[node] == "" && ws == 0) { STOP_T[node] = t; STOP_WHY[node] = "feedback_a_wheel_speed_0" }
    } else if (k == "FEEDBACK_B") {
        if (nsync > 0) { new_node(node); answer(node, "B") }
    } else {
        st = byte(0) % 16
        if (st == 3 && !(node in FAULT_T)) FAULT_T[node] = t
        if ((node in LAST_SP) && STOP_T[node] == "" && st != 2) { STOP_T[node] = t; STOP_WHY[node] = "status_state" st "_fault" byte(1) }
    }
}
END {
    nn = 0; missa = 0; missb = 0
    for (n in NODES) { nn++; missa += PA[n]; missb += PB[n] }
    m = (nsync > 1) ? sum / (nsync - 1) : 0
    v = (nsync > 2) ? (sumsq - (nsync - 1) * m * m) / (nsync - 2) : 0
    if (v < 0) v = 0
    printf "frames=%d\nunparsed=%d\nother=%d\nskipped=%d\nbadctr=%d\n", frames, unparsed, other, skipped, badctr
    printf "sync=%d\nsetpoint=%d\nfeedback_a=%d\nfeedback_b=%d\nstatus=%d\n", COUNT["SYNC"], COUNT["SETPOINT"], COUNT["FEEDBACK_A"], COUNT["FEEDBACK_B"], COUNT["STATUS"]
    printf "nodes=%d\nsetpoint_cycles=%d\nsetpoint_bad_cycles=%d\n", nn, sp_cycles, sp_bad
    printf "missing_a=%d\nmissing_b=%d\nextra_a=%d\nextra_b=%d\nlate_a=%d\nlate_b=%d\nanswer_max_ms=%.3f\n", missa, missb, EXTRA["A"], EXTRA["B"], LATE["A"], LATE["B"], answer_max
    printf "sync_mean_ms=%.4f\nsync_std_ms=%.4f\nsync_min_ms=%.3f\nsync_max_ms=%.3f\n", m, root(v), (nsync > 1) ? dmin : 0, dmax
    worst = -1; moving = 0; disabled = 0; faults = 0
    for (n in NODES) {
        if ((n in FAULT_T) && (n in LAST_SP) && FAULT_T[n] < LAST_SP[n]) faults++
        if (!(n in LAST_SP)) { printf "stop_node%d=no_setpoint\n", n; worst = 1e9; continue }
        if (SPEED_AT_LAST[n] + 0 != 0) moving++
        if (LAST_EN[n] != 1) disabled++
        if (STOP_T[n] == "") {
            printf "stop_node%d=last_setpoint %.6f enable %d, never seen stopped, wheel_speed_raw_before %d\n", n, LAST_SP[n], LAST_EN[n], SPEED_AT_LAST[n]
            worst = 1e9
        } else {
            dt = (STOP_T[n] - LAST_SP[n]) * 1000
            printf "stop_node%d=last_setpoint %.6f enable %d, stopped %.6f, after_ms %.1f, by %s, wheel_speed_raw_before %d\n", n, LAST_SP[n], LAST_EN[n], STOP_T[n], dt, STOP_WHY[n], SPEED_AT_LAST[n]
            if (dt > worst) worst = dt
        }
    }
    printf "fault_during_run=%d\nmoving_nodes=%d\nlast_setpoint_disabled=%d\nworst_stop_ms=%.1f\n", faults, moving, disabled, worst
}
