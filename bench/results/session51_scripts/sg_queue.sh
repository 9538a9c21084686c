# session 51: score_guidance_flow.sh on several runs, one after another on one core.
# usage: bash sg_queue.sh LAMBDA RUN_DIR [RUN_DIR ...]   (venv active)
L=$1; shift
for RUN in "$@"; do
  bash "$(dirname "$0")/score_guidance_flow.sh" $RUN $L
done
