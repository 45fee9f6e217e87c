#!/usr/bin/env bash
# The SocketCAN set, run as root inside a Linux with vcan (a VM booted by
# harness/tools/vcan_check.py, or a machine with SocketCAN): usage `vcan_vm.sh WORK`.
# WORK holds host/ (the local-bus reference, made first: plant_slice.blf is read here) and
# gets vm/ (everything this script writes). Each Python start is slow under QEMU without
# KVM, so the set is few commands: the main job (captured by candump and rhonn-bus dump), a
# warm-bench pair over --bus auto, the controller alone fed by can.player while
# can.logger records, and a flood that a node does not read (its drops counted). The comparisons are made afterwards, on the host (vcan_check.py).
set -u
# job control: without it, background jobs of a script ignore SIGINT, and Python keeps it
# ignored (no KeyboardInterrupt: rhonn-bus dump, can.logger and the controller would not
# close their files on the `stop` below)
set -m
WORK=$(cd "$1" && pwd)
REPO=$(cd "$(dirname "$0")/../.." && pwd)
BIN="$REPO/.venv/bin"
VM="$WORK/vm"
rm -rf "$VM" && mkdir -p "$VM" "$WORK/home"
export HOME="$WORK/home" PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 MPLBACKEND=Agg
# numba keys its cache on the CPU model, which the guest may not share with the host, and
# the package folders are read-only here: a writable cache lets later processes reuse it
export NUMBA_CACHE_DIR="$WORK/numba-cache"
export MPLCONFIGDIR="$WORK/mplconfig"  # its font cache, built by vcan_check.py on the host
cd "$WORK" || exit 3
step() { echo "$(date +%s) $*" >> "$VM/steps.log"; }
# wait_line FILE TEXT S: until FILE has a line starting with TEXT (S wall seconds at most)
wait_line() {
  local i
  for ((i = 0; i < $3 * 10; i++)); do
    grep -q "^$2" "$1" 2>/dev/null && return 0
    sleep 0.1
  done
  return 1
}
# stop PID...: SIGINT (each closes its files), SIGKILL after 60 s for any still running
stop() {
  local i pid alive
  kill -INT "$@" 2>/dev/null
  for ((i = 0; i < 600; i++)); do
    alive=0
    for pid in "$@"; do kill -0 "$pid" 2>/dev/null && alive=1; done
    [ "$alive" = 0 ] && break
    sleep 0.1
  done
  for pid in "$@"; do
    kill -0 "$pid" 2>/dev/null && { step "SIGKILL $pid"; kill -KILL "$pid" 2>/dev/null; }
  done
  wait "$@" 2>/dev/null
}

step "start $(uname -r)"
if [ "${VCAN_SETUP:-1}" = 1 ]; then
  { modprobe vcan && modprobe can_raw && ip link add dev vcan0 type vcan \
      && ip link set up vcan0; } 2> "$VM/setup.err" || { step "setup failed"; exit 3; }
fi
ip -details link show vcan0 > "$VM/vcan0.txt" 2>&1 || { step "no vcan0"; exit 3; }
# python-can's can.logger and can.player take the kernel's default receive buffer (212 kB,
# about 280 CAN frames of 768 bytes); under emulation the logger writing its BLF can fall that
# far behind, and the kernel then drops frames unseen. The VM's default for new sockets is
# raised to 8 MiB; the loop's nodes and the dump set their own buffer (docs/vcan.md).
if [ -w /proc/sys/net/core/rmem_default ]; then
  echo 8388608 > /proc/sys/net/core/rmem_max
  echo 8388608 > /proc/sys/net/core/rmem_default
fi
# the options for a slow machine (docs/cli.md); the CI test key as on the host
RUN_OPTS=(--no-plots --no-rrd --lockstep-wait-ms 2000 --bus-start-timeout 120
          --secoc-keys ci-test-key)

step "main job"
candump -L vcan0 > "$VM/candump.log" & CANDUMP=$!
"$BIN/rhonn-bus" dump --bus socketcan:vcan0 --timeout 7200 --secoc-keys ci-test-key \
  > "$VM/dump.txt" 2> "$VM/dump.err" & DUMP=$!
wait_line "$VM/dump.txt" ready 300 || step "rhonn-bus dump not ready"
"$BIN/rhonn-harness" run dlc-paper --controller nmpc-rhonn --bus socketcan:vcan0 \
  --out "$VM/main" "${RUN_OPTS[@]}" > "$VM/main.out" 2>&1
echo $? > "$VM/main.rc"
sleep 1
stop "$CANDUMP" "$DUMP"

step "warm-bench pair over --bus auto"
"$BIN/rhonn-harness" compare dlc-paper --controllers lmpc,nmpc-rhonn --bus auto \
  --duration "${PAIR_DURATION_S:-2}" --out "$VM/pair" "${RUN_OPTS[@]}" > "$VM/pair.out" 2>&1
echo $? > "$VM/pair.rc"

step "controller alone, fed by can.player, recorded by can.logger"
"$BIN/rhonn-controller" --bus socketcan:vcan0 --controller nmpc-rhonn --mode lockstep \
  --secoc --secoc-keys ci-test-key --summary "$VM/alone_summary.json" \
  > "$VM/alone.out" 2> "$VM/alone.err" & ALONE=$!
"$BIN/python" -m can.logger -i socketcan -c vcan0 -f "$VM/roundtrip.blf" \
  > "$VM/logger.out" 2>&1 & LOGGER=$!
wait_line "$VM/alone.out" ready 300 || step "controller not ready"
wait_line "$VM/logger.out" Connected 300 || step "can.logger not ready"
# a gap per frame that the controller keeps up with under emulation (answers are compared,
# not their timing)
"$BIN/python" -m can.player -i socketcan -c vcan0 -g "${PLAYER_GAP_S:-0.008}" \
  "$WORK/host/plant_slice.blf" > "$VM/player.out" 2>&1
echo $? > "$VM/player.rc"
sleep 2
stop "$LOGGER" "$ALONE"
step "flood: drops counted"
"$BIN/python" -m harness.tools.vcan_drops --bus socketcan:vcan0 --frames 20000 \
  --out "$VM/drops.json" > "$VM/drops.out" 2>&1
step "done"
