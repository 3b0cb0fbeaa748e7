# Shared by scripts/container-check.sh and scripts/container-cuda-check.sh (sourced from the
# repository root): the engine, a scratch folder and the containers a check started, removed on
# exit, and the steps both take.
C=${CONTAINER:-docker}
work=$(mktemp -d)
names=()
cleanup() {
  for n in "${names[@]}"; do "$C" rm -f "$n" >/dev/null 2>&1 || true; done
  rm -rf "$work"
}
trap cleanup EXIT
fail() { echo "FAIL: $*" >&2; exit 1; }
step() { echo "== $*"; }
# Waits up to 120 s for /readyz on PORT; fails with container NAME's last log lines, at once if it
# stopped.
wait_ready() {
  for _ in $(seq 120); do
    curl -fsS "http://127.0.0.1:$1/readyz" >/dev/null 2>&1 && return 0
    "$C" inspect --format '{{.State.Running}}' "$2" 2>/dev/null | grep -q true \
      || fail "$2 stopped: $("$C" logs "$2" 2>&1 | tail -n 5)"
    sleep 1
  done
  fail "not ready after 120 s: $("$C" logs "$2" 2>&1 | tail -n 5)"
}
# Simulated request frames written by IMAGE's own binary; sets `frame` to the first one.
simulate_frame() {
  chmod 0777 "$work"
  "$C" run --rm -v "$work:/out" "$1" simulate --count 4 --seed 7 --image-size 64 --requests 4 \
    --profile street --out /out/sim >"$work/simulate.log" 2>&1 \
    || fail "the simulator failed: $(tail -n 3 "$work/simulate.log")"
  frame=$(ls "$work"/sim/requests/*.json | head -n 1)
  [ -f "$frame" ] || fail "the simulator wrote no request fixture"
}
