# session 52: wait for a rebuild (rebuild.sh) to finish (or resume a killed one), then variant.sh on it.
# usage: bash chain.sh TASK NOISE SEED STEPS NAME OVERRIDE [OVERRIDE ...]   (venv active; one core)
T=$1; N=$2; S=$3; P=$4; NAME=$5; shift 5
D=$(dirname "$0"); W=/work/runs/room_s52/${T}_e${N}_s${S}_v${P}
while pgrep -f "run_dir=$W " > /dev/null; do sleep 30; done
if ! grep -q '"diffuser"' $W/stages.json 2>/dev/null; then  # killed before the diffuser finished: resume it
  . $D/../session43_scripts/common.sh
  python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W stop_after=diffuser resume=true "$V" >> $W.log 2>&1 || exit 1
fi
bash $D/variant.sh $W $NAME "$@"
