#!/usr/bin/env bash
# Two-host recipe on one machine: the operator and the teleoperator in two network namespaces joined
# by a veth pair, talking UDP over it, as on two hosts. Needs root (ip netns) and iproute2.
#
#   sudo deploy/netns/udp.sh            # env: TELEOP (command, default: teleop), OUT (default ./netns-udp),
#                                       #      KEY (OUT/teleop.key), CODEC (eds:50), SCENARIO (protocol), DURATION (15), NETEM ("")
#
# Addresses live only inside the two namespaces this script creates (10.77.0.1 and 10.77.0.2) and
# are removed with them on exit, whatever happens.
set -euo pipefail
TELEOP=${TELEOP:-teleop}
OUT=${OUT:-netns-udp}
CODEC=${CODEC:-eds:50}
SCENARIO=${SCENARIO:-protocol}
DURATION=${DURATION:-15}
NETEM=${NETEM:-}
KEY=${KEY:-$OUT/teleop.key}  # the pre-shared key both sides prove (made here if missing)
[ "$(id -u)" = 0 ] || { echo "udp.sh: needs root (ip netns add)" >&2; exit 2; }
command -v ip >/dev/null || { echo "udp.sh: needs iproute2 (apt-get install iproute2)" >&2; exit 2; }

tag=$$
NS_OP=teleop-op-$tag
NS_TO=teleop-to-$tag
pids=()
cleanup() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  wait 2>/dev/null || true
  ip netns del "$NS_OP" 2>/dev/null || true
  ip netns del "$NS_TO" 2>/dev/null || true
}
trap cleanup EXIT INT TERM

ip netns add "$NS_OP"
ip netns add "$NS_TO"
ip link add "vop$tag" type veth peer name "vto$tag"
ip link set "vop$tag" netns "$NS_OP"
ip link set "vto$tag" netns "$NS_TO"
ip -n "$NS_OP" addr add 10.77.0.1/30 dev "vop$tag"
ip -n "$NS_TO" addr add 10.77.0.2/30 dev "vto$tag"
for ns in "$NS_OP" "$NS_TO"; do ip -n "$ns" link set lo up; done
ip -n "$NS_OP" link set "vop$tag" up
ip -n "$NS_TO" link set "vto$tag" up

mkdir -p "$OUT/logs"
[ -f "$KEY" ] || "$TELEOP" keygen "$KEY" >/dev/null
rm -f "$OUT"/logs/{operator,teleoperator}.{json,mcap}
ip netns exec "$NS_TO" "$TELEOP" teleoperator --key-file "$KEY" --listen 10.77.0.2:7000 --log "$OUT/logs" --quiet &
pids+=($!)
sleep 0.5
ip netns exec "$NS_OP" "$TELEOP" operator --key-file "$KEY" --peer 10.77.0.2:7000 --listen 10.77.0.1:0 --log "$OUT/logs" \
  --codec "$CODEC" --scenario "$SCENARIO" --duration "$DURATION" ${NETEM:+--netem "$NETEM"} --quiet \
  || [ $? -eq 3 ]  # 3: a poor session (teleop/session/verdict.py), recorded whole: the report says why
wait "${pids[0]}" || [ $? -eq 3 ]
pids=()
"$TELEOP" report "$OUT/logs" --out "$OUT" --transport udp
