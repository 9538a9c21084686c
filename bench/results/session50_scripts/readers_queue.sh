# session 50: session 49's readers reading (shooting, 4 candidates, each generated path read 4 times) of more runs,
# one after another on one core.  usage: bash readers_queue.sh RUN_DIR:NAME [RUN_DIR:NAME ...]  (venv active)
for cell in "$@"; do
  bash bench/results/session49_scripts/readers.sh ${cell%%:*} ${cell##*:} bench/results/readers_s50
done
