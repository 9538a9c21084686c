# session 53: a rebuilt run (session52_scripts/rebuild.sh) copied and redone from the flow with extra overrides: flow,
# BC and evaluation only (no open-loop replay, no readers reading), for BC's spread (bc_spread.sh).
# usage: bash flow_only.sh RUN_DIR NAME OVERRIDE [OVERRIDE ...]  (venv active; one core) -> /work/runs/room_s53/<run>_<NAME>
OUT=/work/runs/room_s53 READ=none bash "$(dirname "$0")/../session52_scripts/variant.sh" "$1" "$2" \
  analysis.open_loop=false "${@:3}"
