#!/usr/bin/env bash
# Run rollbase against the real Linux SocketCAN stack (vcan0), on machines without kernel CAN.
#
# When this machine has a usable vcan0 (`ip link show vcan0` works and it is up), the checks in
# scripts/vcan-vm/checks.sh run directly on the host. Otherwise a small VM is booted:
#
#   Debian's kernel package (apt-get download linux-image-6.1.0-*-amd64) provides vmlinuz and
#   can.ko, can-raw.ko, can-dev.ko, vcan.ko; an initramfs is packed with busybox-static, iproute2's
#   `ip`, can-utils (candump/cansend/cangen), the workspace's release binaries (rollbase,
#   rollbase-sim) and the driver's SocketCAN test binaries, each with the shared libraries `ldd`
#   lists; qemu-system-x86_64 boots it under TCG (KVM is not used: it hangs on the CI machines),
#   the guest /init (scripts/vcan-vm/init) loads the modules, brings vcan0 up and runs the checks,
#   prints `VCAN-VM-RESULT: pass|fail P/N` and powers off.
#
# The guest console is streamed to stdout (and saved as $WORK/console.log). Exit status: 0 when
# every check passed; 1 when a check failed, the result line is missing, or the guest timed out;
# 2 on a setup error (missing tool, build failure).
#
# Usage: scripts/vcan-vm.sh [--vm|--host] [--no-build] [--timeout SECONDS] [--keep]
#                           [--checks "0 1 2 3 4 5 6 7 8"]
#   --vm / --host   force the VM, or force running on the host (needs vcan0)
#   --no-build      use the binaries already in target/release instead of building them (the
#                   SocketCAN test binaries still come from `cargo test --no-run`, a no-op when
#                   they are up to date)
#   --timeout S     give up on the guest after S seconds (default 600)
#   --keep          keep the work directory (initramfs tree, console log)
#   --checks LIST   run only these checks (default: all; 0 is the kernel/can-utils smoke test)
# Environment: XDG_CACHE_HOME (cache root; default ~/.cache), ROLLBASE_VCAN_VM_CACHE (cache dir,
# default $XDG_CACHE_HOME/rollbase-vcan-vm), ROLLBASE_VCAN_VM_MEM (MiB, default 1024),
# ROLLBASE_VCAN_VM_SMP (default 2), ROLLBASE_VCAN_VM_NICE (qemu's nice value when root, default
# -10), CARGO_BUILD_JOBS (default 2), ROLLBASE_DURATION (seconds of
# the seed-000 run in checks 2-4; default: the whole scenario), ROLLBASE_VCAN_VM_EXTRA (a shell
# command the guest runs before the checks, for debugging; no single quotes).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
HERE="$ROOT/scripts/vcan-vm"
MODE=auto
BUILD=1
TIMEOUT=600
KEEP=0
CHECKS="${ROLLBASE_VCAN_CHECKS:-}"
while [ $# -gt 0 ]; do
    case "$1" in
        --vm) MODE=vm ;;
        --host) MODE=host ;;
        --no-build) BUILD=0 ;;
        --timeout) TIMEOUT="${2:?--timeout needs a number of seconds}"; shift ;;
        --keep) KEEP=1 ;;
        --checks) CHECKS="${2:?--checks needs a list like \"0 1 2\"}"; shift ;;
        -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
        *) echo "vcan-vm: unknown argument $1 (see --help)" >&2; exit 2 ;;
    esac
    shift
done
case "$TIMEOUT" in ''|*[!0-9]*) echo "vcan-vm: --timeout $TIMEOUT: give whole seconds" >&2; exit 2 ;; esac

JOBS="${CARGO_BUILD_JOBS:-2}"
CACHE="${ROLLBASE_VCAN_VM_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/rollbase-vcan-vm}"
MEM="${ROLLBASE_VCAN_VM_MEM:-1024}"
SMP="${ROLLBASE_VCAN_VM_SMP:-2}"
T_START=$(date +%s)

log() { printf '[vcan-vm %4ss] %s\n' "$(( $(date +%s) - T_START ))" "$*"; }
die() { printf 'vcan-vm: error: %s\n' "$*" >&2; exit 2; }

host_has_vcan0() {
    command -v ip >/dev/null 2>&1 || return 1
    ip link show vcan0 >/dev/null 2>&1 || return 1
    # vcan0 exists; it must also be usable (up) for the checks.
    ip link show vcan0 | grep -q '[<,]UP[,>]'
}

if [ "$MODE" = auto ]; then
    if host_has_vcan0; then MODE=host; else MODE=vm; fi
fi
log "mode: $MODE"

# ---------------------------------------------------------------------------------------------
# Build the workspace's release binaries and the driver's SocketCAN test binaries.
# ---------------------------------------------------------------------------------------------
TEST_BINS=()
BUILD_FAILED=""
build() {
    cd "$ROOT"
    if [ "$BUILD" = 1 ]; then
        # Each binary on its own: when one does not build, the checks that need it fail (and
        # say so) while the others still run.
        log "cargo build -j$JOBS --release --bin rollbase"
        cargo build -j"$JOBS" --release -p rollbase --bin rollbase >&2 \
            || { log "error: building rollbase failed"; BUILD_FAILED="$BUILD_FAILED rollbase"; }
        log "cargo build -j$JOBS --release --bin rollbase-sim"
        cargo build -j"$JOBS" --release -p rollbase-vcan-sim --bin rollbase-sim >&2 \
            || { log "error: building rollbase-sim failed"; BUILD_FAILED="$BUILD_FAILED rollbase-sim"; }
    fi
    # The driver's SocketCAN integration tests: driver/tests/*socketcan*.rs and *vcan*.rs (cargo
    # names an integration test after its file). Only those are built (in release, like the
    # binaries), and the executables are taken from cargo's JSON messages.
    local f args=() json line name exe
    for f in "$ROOT"/driver/tests/*.rs; do
        [ -e "$f" ] || continue
        name="$(basename "$f" .rs)"
        case "$name" in *socketcan*|*vcan*) args+=(--test "$name") ;; esac
    done
    if [ "${#args[@]}" -gt 0 ]; then
        json="$(mktemp)"
        log "cargo test -j$JOBS --release -p rollbase-driver ${args[*]} --no-run"
        cargo test -j"$JOBS" --release -p rollbase-driver "${args[@]}" --no-run --message-format=json >"$json" \
            || { log "error: building the driver's SocketCAN tests failed"; BUILD_FAILED="$BUILD_FAILED driver-tests"; }
        while IFS= read -r line; do
            name="$(printf '%s\n' "$line" | sed -n 's/.*"target":{[^}]*"name":"\([^"]*\)".*/\1/p')"
            exe="$(printf '%s\n' "$line" | sed -n 's/.*"executable":"\([^"]*\)".*/\1/p')"
            case "$name" in *socketcan*|*vcan*) ;; *) continue ;; esac
            [ -n "$exe" ] && [ -x "$exe" ] && TEST_BINS+=("$name=$exe")
        done < <(grep '"reason":"compiler-artifact"' "$json" | grep '"test":true')
        rm -f "$json"
    fi
    for b in rollbase rollbase-sim; do
        [ -x "$ROOT/target/release/$b" ] || log "warning: target/release/$b missing (checks needing it will fail)"
    done
    [ "${#TEST_BINS[@]}" -gt 0 ] || log "warning: no SocketCAN test binary found in rollbase-driver (check 1 will fail)"
    for t in "${TEST_BINS[@]}"; do log "SocketCAN test binary: ${t%%=*} -> ${t#*=}"; done
}

# ---------------------------------------------------------------------------------------------
# Host mode: run the checks directly against this machine's vcan0.
# ---------------------------------------------------------------------------------------------
if [ "$MODE" = host ]; then
    host_has_vcan0 || die "no usable vcan0 on this machine: create it with \
'sudo modprobe vcan && sudo ip link add dev vcan0 type vcan && sudo ip link set up vcan0', or use --vm"
    for t in candump cansend ip; do command -v "$t" >/dev/null || die "$t not found (install can-utils / iproute2)"; done
    build
    WORK="$(mktemp -d "${TMPDIR:-/tmp}/rollbase-vcan-host.XXXXXX")"
    mkdir -p "$WORK/tests"
    for t in "${TEST_BINS[@]}"; do cp "${t#*=}" "$WORK/tests/${t%%=*}"; done
    log "running the checks on the host's vcan0 (work dir $WORK)"
    set +e
    ROLLBASE_BIN="$ROOT/target/release" ROLLBASE_TESTS="$WORK/tests" ROLLBASE_WORK="$WORK" \
        ROLLBASE_CHECKS="$CHECKS" ROLLBASE_CHECKS_AWK="$HERE/capture.awk" \
        sh "$HERE/checks.sh" 2>&1 | tee "$WORK/console.log"
    set -e
    res="$(tr -d '\r' <"$WORK/console.log" | sed -n 's/^.*\(VCAN-VM-RESULT: .*\)$/\1/p' | tail -n 1)"
    [ "$KEEP" = 1 ] || rm -rf "$WORK"
    log "total $(( $(date +%s) - T_START )) s"
    [ -z "$BUILD_FAILED" ] || { log "FAIL: build failed for:$BUILD_FAILED ($res)"; exit 1; }
    case "$res" in
        "VCAN-VM-RESULT: pass "*) log "$res"; exit 0 ;;
        "") log "no result line from the checks"; exit 1 ;;
        *) log "$res"; exit 1 ;;
    esac
fi

# ---------------------------------------------------------------------------------------------
# VM mode.
# ---------------------------------------------------------------------------------------------
need_pkgs=()
command -v file >/dev/null || need_pkgs+=(file)
command -v qemu-system-x86_64 >/dev/null || need_pkgs+=(qemu-system-x86)
static_busybox() {
    local b
    for b in /bin/busybox /usr/bin/busybox; do
        if [ -x "$b" ] && command -v file >/dev/null && file -L "$b" | grep -q 'statically linked'; then
            echo "$b"; return 0
        fi
    done
    return 1
}
static_busybox >/dev/null || need_pkgs+=(busybox-static)
command -v candump >/dev/null || need_pkgs+=(can-utils)
command -v cpio >/dev/null || need_pkgs+=(cpio)
command -v ip >/dev/null || need_pkgs+=(iproute2)
if [ "${#need_pkgs[@]}" -gt 0 ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        log "installing ${need_pkgs[*]} with apt-get"
        apt-get update -q >&2 || true
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${need_pkgs[@]}" >&2 \
            || die "apt-get install ${need_pkgs[*]} failed"
    else
        die "missing: ${need_pkgs[*]}; install them (e.g. sudo apt-get install ${need_pkgs[*]})"
    fi
fi
BUSYBOX="$(static_busybox)" || die "no statically linked busybox found (install busybox-static)"

# --- kernel and CAN modules, cached ------------------------------------------------------------
mkdir -p "$CACHE/debs"
KVER_FILE="$CACHE/kernel/version"
fetch_kernel() {
    command -v apt-get >/dev/null || die "apt-get not found: put vmlinuz and the CAN modules in $CACHE/kernel by hand"
    local pkg deb
    # linux-image-amd64 is a metapackage; its dependency is the real kernel package.
    pkg="$(apt-cache depends linux-image-amd64 2>/dev/null | sed -n 's/^ *Depends: \(linux-image-[0-9][^ ]*-amd64\)$/\1/p' | head -n 1)"
    [ -n "$pkg" ] || die "apt-cache depends linux-image-amd64 names no linux-image-*-amd64 package (run apt-get update?)"
    deb="$(ls "$CACHE/debs/${pkg}"_*.deb 2>/dev/null | head -n 1 || true)"
    if [ -z "$deb" ]; then
        log "apt-get download $pkg"
        (cd "$CACHE/debs" && apt-get download "$pkg" >&2) || die "apt-get download $pkg failed"
        deb="$(ls "$CACHE/debs/${pkg}"_*.deb | head -n 1)"
    fi
    log "unpacking vmlinuz and the CAN modules from $(basename "$deb")"
    local tmp
    tmp="$(mktemp -d "$CACHE/unpack.XXXXXX")"
    dpkg-deb --fsys-tarfile "$deb" | tar -x -C "$tmp" --wildcards './boot/vmlinuz-*' '*/net/can/*' \
        || die "unpacking $deb failed"
    rm -rf "$CACHE/kernel"
    mkdir -p "$CACHE/kernel/modules"
    cp "$tmp"/boot/vmlinuz-* "$CACHE/kernel/vmlinuz"
    local m f
    for m in can can-raw can-dev vcan; do
        f="$(find "$tmp/lib/modules" -name "$m.ko" -o -name "$m.ko.xz" -o -name "$m.ko.zst" -o -name "$m.ko.gz" | head -n 1)"
        [ -n "$f" ] || die "$m.ko not found in $deb"
        case "$f" in
            *.xz) xz -dc "$f" >"$CACHE/kernel/modules/$m.ko" ;;
            *.zst) zstd -dqc "$f" >"$CACHE/kernel/modules/$m.ko" ;;
            *.gz) gzip -dc "$f" >"$CACHE/kernel/modules/$m.ko" ;;
            *) cp "$f" "$CACHE/kernel/modules/$m.ko" ;;
        esac
    done
    basename "$deb" >"$KVER_FILE"
    rm -rf "$tmp"
}
if [ ! -s "$KVER_FILE" ] || [ ! -s "$CACHE/kernel/vmlinuz" ] || [ ! -s "$CACHE/kernel/modules/vcan.ko" ]; then
    fetch_kernel
else
    log "kernel from cache: $(cat "$KVER_FILE")"
fi

build

# --- initramfs ---------------------------------------------------------------------------------
WORK="$(mktemp -d "${TMPDIR:-/tmp}/rollbase-vcan-vm.XXXXXX")"
cleanup() { if [ "$KEEP" = 1 ]; then log "kept $WORK"; else rm -rf "$WORK"; fi; }
trap cleanup EXIT
R="$WORK/root"
mkdir -p "$R"/{bin,sbin,lib,lib64,usr/bin,usr/sbin,proc,sys,dev,tmp,run,etc,rollbase/bin,rollbase/tests,lib/modules}
cp "$BUSYBOX" "$R/bin/busybox"
for app in $("$BUSYBOX" --list); do
    [ -e "$R/bin/$app" ] || ln -s busybox "$R/bin/$app"
done
# Libraries: copy what ldd lists, at the same absolute paths, plus the dynamic loader.
copy_with_libs() { # src dest
    local src="$1" dest="$2" lib
    if file -L "$src" | grep -q 'not stripped\|with debug_info'; then
        strip --strip-debug -o "$R$dest" "$src" 2>/dev/null || cp "$src" "$R$dest"
    else
        cp "$src" "$R$dest"
    fi
    chmod 755 "$R$dest"
    for lib in $(ldd "$src" 2>/dev/null | sed -n 's/.*=> \(\/[^ ]*\) .*/\1/p; s/^[[:space:]]*\(\/[^ ]*\) (.*/\1/p'); do
        if [ ! -e "$R$lib" ]; then
            mkdir -p "$R$(dirname "$lib")"
            cp -L "$lib" "$R$lib"
        fi
    done
}
# iproute2's ip (busybox's applet cannot create vcan links) replaces the busybox symlink.
rm -f "$R/bin/ip"
copy_with_libs "$(command -v ip)" /sbin/ip
for t in candump cansend cangen; do copy_with_libs "$(command -v "$t")" "/usr/bin/$t"; done
for b in rollbase rollbase-sim; do
    case " $BUILD_FAILED " in *" $b "*) log "not packing $b (its build failed)"; continue ;; esac
    if [ -x "$ROOT/target/release/$b" ]; then copy_with_libs "$ROOT/target/release/$b" "/rollbase/bin/$b"; fi
done
for t in "${TEST_BINS[@]}"; do copy_with_libs "${t#*=}" "/rollbase/tests/${t%%=*}"; done
for m in can can-raw can-dev vcan; do cp "$CACHE/kernel/modules/$m.ko" "$R/lib/modules/"; done
cp "$HERE/init" "$R/init"
cp "$HERE/checks.sh" "$R/rollbase/checks.sh"
cp "$HERE/capture.awk" "$R/rollbase/capture.awk"
chmod 755 "$R/init"
{   # settings for the guest's checks.sh (sourced by /init)
    printf "ROLLBASE_CHECKS='%s'\n" "$CHECKS"
    printf "ROLLBASE_DURATION='%s'\n" "${ROLLBASE_DURATION:-}"
    printf "ROLLBASE_VCAN_VM_EXTRA='%s'\n" "${ROLLBASE_VCAN_VM_EXTRA:-}"
} >"$R/rollbase/checks.env"
printf 'root:x:0:0:root:/root:/bin/sh\n' >"$R/etc/passwd"
printf 'root:x:0:\n' >"$R/etc/group"
# /dev/console for the kernel's first open (the init also mounts devtmpfs and re-opens it).
mknod -m 600 "$R/dev/console" c 5 1 2>/dev/null || true
mknod -m 666 "$R/dev/null" c 1 3 2>/dev/null || true
(cd "$R" && find . -print0 | cpio --null -o -H newc --quiet | gzip -1 >"$WORK/initrd.gz")
log "initramfs: $(du -h "$WORK/initrd.gz" | cut -f1) compressed ($(du -sh "$R" | cut -f1) unpacked)"

# --- boot ----------------------------------------------------------------------------------------
QEMU=(qemu-system-x86_64 -accel tcg -m "$MEM" -smp "$SMP" -kernel "$CACHE/kernel/vmlinuz"
      -initrd "$WORK/initrd.gz" -append "console=ttyS0 quiet panic=-1 rdinit=/init clocksource=tsc tsc=reliable preempt=full"
      -nographic -no-reboot -nic none ${ROLLBASE_VCAN_VM_QEMU_EXTRA:-})
# The checks are real-time (250 Hz) inside an emulated machine: when root, give qemu a head
# start over other work on this machine (ROLLBASE_VCAN_VM_NICE, default -10; 0 to disable).
NICE="${ROLLBASE_VCAN_VM_NICE:--10}"
if [ "$(id -u)" = 0 ] && [ "$NICE" != 0 ]; then QEMU=(nice -n "$NICE" "${QEMU[@]}"); fi
# The guest's 250 Hz loop shares this machine's cores with everything else: a busy host shows up
# as late SYNCs and stale feedback inside the guest. Say so up front.
LOAD="$(cut -d' ' -f1 /proc/loadavg 2>/dev/null || echo 0)"
CORES="$(nproc 2>/dev/null || echo 1)"
log "host load average $LOAD on $CORES cores"
if awk -v l="$LOAD" -v c="$CORES" 'BEGIN { exit !(l > c * 0.75) }'; then
    log "warning: the host is busy (load $LOAD on $CORES cores); the real-time checks (2, 3, 5) may fail for lack of CPU, not because of rollbase"
fi
log "booting: ${QEMU[*]}"
T_BOOT=$(date +%s)
set +e
timeout --foreground -k 10 "$TIMEOUT" "${QEMU[@]}" </dev/null 2>&1 | tee "$WORK/console.log"
rc_qemu=${PIPESTATUS[0]}
set -e
T_END=$(date +%s)
res="$(tr -d '\r' <"$WORK/console.log" | sed -n 's/^.*\(VCAN-VM-RESULT: .*\)$/\1/p' | tail -n 1)"
log "guest ran $((T_END - T_BOOT)) s (qemu exit status $rc_qemu); whole VM stage $((T_END - T_START)) s"
if [ "$rc_qemu" = 124 ] || [ "$rc_qemu" = 137 ]; then
    log "FAIL: the guest did not finish within $TIMEOUT s"
    exit 1
fi
[ -z "$BUILD_FAILED" ] || { log "FAIL: build failed for:$BUILD_FAILED ($res)"; exit 1; }
case "$res" in
    "VCAN-VM-RESULT: pass "*) log "$res"; exit 0 ;;
    "") log "FAIL: no VCAN-VM-RESULT line in the guest output"; exit 1 ;;
    *) log "FAIL: $res"; exit 1 ;;
esac
