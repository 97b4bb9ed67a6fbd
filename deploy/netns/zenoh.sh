#!/usr/bin/env bash
# Three-host recipe on one machine: operator, teleoperator and a Zenoh router in three network
# namespaces; the operator and the teleoperator each reach the router over their own veth pair and
# talk through it as Zenoh clients. Needs root (ip netns) and iproute2.
#
#   sudo deploy/netns/zenoh.sh          # env: TELEOP (command, default: teleop), OUT (default ./netns-zenoh),
#                                       #      KEY (OUT/teleop.key), CODEC (eds:50), SCENARIO (protocol), DURATION (15), NETEM ("")
#
# Addresses live only inside the namespaces this script creates (10.77.1.0/30 operator-router,
# 10.77.2.0/30 teleoperator-router) and are removed with them on exit, whatever happens.
set -euo pipefail
TELEOP=${TELEOP:-teleop}
OUT=${OUT:-netns-zenoh}
CODEC=${CODEC:-eds:50}
SCENARIO=${SCENARIO:-protocol}
DURATION=${DURATION:-15}
NETEM=${NETEM:-}
KEY=${KEY:-$OUT/teleop.key}  # the pre-shared key both sides prove (made here if missing)
[ "$(id -u)" = 0 ] || { echo "zenoh.sh: needs root (ip netns add)" >&2; exit 2; }
command -v ip >/dev/null || { echo "zenoh.sh: needs iproute2 (apt-get install iproute2)" >&2; exit 2; }

tag=$$
NS_OP=teleop-op-$tag
NS_TO=teleop-to-$tag
NS_RT=teleop-rt-$tag
pids=()
cleanup() {
  for p in "${pids[@]}"; do kill -INT "$p" 2>/dev/null || true; done
  wait 2>/dev/null || true
  for ns in "$NS_OP" "$NS_TO" "$NS_RT"; do ip netns del "$ns" 2>/dev/null || true; done
}
trap cleanup EXIT INT TERM

for ns in "$NS_OP" "$NS_TO" "$NS_RT"; do ip netns add "$ns"; ip -n "$ns" link set lo up; done
# operator <-> router
ip link add "zop$tag" type veth peer name "zro$tag"
ip link set "zop$tag" netns "$NS_OP"; ip link set "zro$tag" netns "$NS_RT"
ip -n "$NS_OP" addr add 10.77.1.1/30 dev "zop$tag"; ip -n "$NS_RT" addr add 10.77.1.2/30 dev "zro$tag"
ip -n "$NS_OP" link set "zop$tag" up; ip -n "$NS_RT" link set "zro$tag" up
# teleoperator <-> router
ip link add "zto$tag" type veth peer name "zrt$tag"
ip link set "zto$tag" netns "$NS_TO"; ip link set "zrt$tag" netns "$NS_RT"
ip -n "$NS_TO" addr add 10.77.2.1/30 dev "zto$tag"; ip -n "$NS_RT" addr add 10.77.2.2/30 dev "zrt$tag"
ip -n "$NS_TO" link set "zto$tag" up; ip -n "$NS_RT" link set "zrt$tag" up

mkdir -p "$OUT/logs"
[ -f "$KEY" ] || "$TELEOP" keygen "$KEY" >/dev/null
rm -f "$OUT"/logs/{operator,teleoperator}.{json,mcap}
ip netns exec "$NS_RT" "$TELEOP" router --listen tcp/10.77.1.2:7447 --listen tcp/10.77.2.2:7447 &
pids+=($!)
sleep 1
Z=(--transport zenoh --zenoh-mode client --zenoh-prefix teleop/netns)
ip netns exec "$NS_TO" "$TELEOP" teleoperator --key-file "$KEY" "${Z[@]}" --zenoh-router tcp/10.77.2.2:7447 --log "$OUT/logs" --quiet &
to_pid=$!
pids+=("$to_pid")
sleep 0.5
ip netns exec "$NS_OP" "$TELEOP" operator --key-file "$KEY" "${Z[@]}" --zenoh-router tcp/10.77.1.2:7447 --log "$OUT/logs" \
  --codec "$CODEC" --scenario "$SCENARIO" --duration "$DURATION" ${NETEM:+--netem "$NETEM"} --quiet \
  || [ $? -eq 3 ]  # 3: a poor session (teleop/session/verdict.py), recorded whole: the report says why
wait "$to_pid" || [ $? -eq 3 ]
"$TELEOP" report "$OUT/logs" --out "$OUT" --transport zenoh
