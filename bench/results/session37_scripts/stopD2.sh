while ! pgrep -f "kinds synthetic" >/dev/null; do sleep 10; done
pkill -f "sh /work/scratch/s37/D2.sh"; echo stopped D2 shell at $(date)
