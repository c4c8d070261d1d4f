#!/bin/sh
# Runs the rollbase-driver SocketCAN tests against a real kernel vcan0 inside a small QEMU VM
# (for machines whose kernel lacks CAN; see DESIGN.md). Needs: qemu-system-x86, busybox-static,
# can-utils, iproute2, cpio (apt-get install --no-install-recommends ...).
# Usage: driver/scripts/vcan-vm.sh [workdir]   (from the repository root)
set -eu
WORK=${1:-/tmp/rollbase-vcan-vm}
mkdir -p "$WORK"
ROOT=$(pwd)
BIN=$(cargo test -p rollbase-driver --test socketcan --no-run --message-format=json 2>/dev/null |
  grep '"executable":"[^"]*socketcan-[^"]*"' | sed 's/.*"executable":"\([^"]*\)".*/\1/' | tail -n 1)
[ -x "$BIN" ] || { echo "could not build the socketcan test binary" >&2; exit 1; }
cd "$WORK"
if ! ls linux-image-*.deb >/dev/null 2>&1; then
  PKG=$(apt-cache depends linux-image-amd64 | grep -o 'linux-image-[0-9][^ ]*' | head -n 1)
  apt-get download "$PKG"
fi
rm -rf kroot initrd && mkdir kroot && dpkg -x linux-image-*.deb kroot
KVER=$(ls kroot/lib/modules | head -n 1)
M=kroot/lib/modules/$KVER/kernel
mkdir -p initrd/bin initrd/proc initrd/sys initrd/dev initrd/tmp initrd/mods
cp /bin/busybox initrd/bin/
for a in sh mount insmod sleep cat kill echo; do ln -sf busybox "initrd/bin/$a"; done
cp "$M/net/can/can.ko" "$M/net/can/can-raw.ko" "$M/drivers/net/can/dev/can-dev.ko" \
   "$M/drivers/net/can/vcan.ko" initrd/mods/
cp "$(command -v ip)" "$(command -v candump)" "$(command -v cansend)" initrd/bin/
cp "$BIN" initrd/bin/socketcan_test
for b in initrd/bin/ip initrd/bin/candump initrd/bin/cansend initrd/bin/socketcan_test; do
  ldd "$b" | grep -o '/[^ ]*'
done | sort -u | while read -r l; do mkdir -p "initrd$(dirname "$l")"; cp -L "$l" "initrd$l"; done
cat > initrd/init <<'INIT'
#!/bin/sh
mount -t proc proc /proc; mount -t sysfs sys /sys; mount -t devtmpfs dev /dev
for m in can can-raw can-dev vcan; do insmod /mods/$m.ko || echo "insmod $m failed"; done
ip link add dev vcan0 type vcan && ip link set up vcan0 && echo "VCAN0 UP"
candump -L vcan0 > /tmp/capture.log & CD=$!
sleep 1
echo "=== rollbase socketcan tests ==="
/bin/socketcan_test --test-threads=1 --nocapture 2>&1
cansend vcan0 703#93027DC0126F
sleep 1; kill $CD
echo "=== capture begin ==="; cat /tmp/capture.log; echo "=== capture end ==="
echo o > /proc/sysrq-trigger
INIT
chmod +x initrd/init
(cd initrd && find . | cpio -o -H newc 2>/dev/null | gzip > ../initrd.gz)
timeout 300 qemu-system-x86_64 -accel tcg -m 512 -kernel "kroot/boot/vmlinuz-$KVER" \
  -initrd initrd.gz -append "console=ttyS0 quiet panic=-1" -nographic -no-reboot | tr -d '\r' | tee vm.log
sed -n '/=== capture begin ===/,/=== capture end ===/p' vm.log | grep '^(' > capture.log || true
echo "candump capture decoded by rollbase:"
(cd "$ROOT" && cargo run -q -p rollbase-driver --example decode_log < "$WORK/capture.log")
grep -q "test result: ok" vm.log
