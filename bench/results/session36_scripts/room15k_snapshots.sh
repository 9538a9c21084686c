#!/bin/bash
# Copy the run's diffuser checkpoint at steps 3000, 6000, 9000, 12000 (written atomically every 1000 steps).
RUN=/work/runs/room_s36/cells/drawer-open-v3/success/ftb/seed4
CK=$RUN/checkpoints/diffuser/diffuser_last.pt
while true; do
  if [ -f "$CK" ]; then
    tmp=/work/runs/room_s36/snap_tmp.pt; cp "$CK" $tmp
    s=$(/work/main/.venv/bin/python -c "import torch;print(int(torch.load('$tmp',weights_only=True)['step']))" 2>/dev/null)
    for t in 3000 6000 9000 12000; do
      if [ "$s" = "$t" ] && [ ! -f /work/runs/room_s36/snap_$t/diffuser_last.pt ]; then
        mkdir -p /work/runs/room_s36/snap_$t; cp $tmp /work/runs/room_s36/snap_$t/diffuser_last.pt; echo "snap $t $(date)"
      fi
    done
    [ "$s" -ge 15000 ] 2>/dev/null && exit 0
  fi
  sleep 60
done
