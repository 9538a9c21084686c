# session 51: BENCHMARKS' two tables from the committed files. usage: bash tables.sh   (from the repository root)
# 1. the conditioning bench sweep (sg_sweep.sh) and the inpaint_start pair
D=bench/results/diffuser_conditioning; S=bench/results/session51_scripts
args=()
for s in 4 5 6 7 8; do for L in 0 0.1 0.3 1; do
  args+=("button-press s$s=$D/button-press-v3-button-press-v3_e4_s${s}_v4500_tracked-sg$L-s51.json"); done; done
for L in 0 0.1 0.3 1; do args+=("drawer-open s4=$D/drawer-open-v3-drawer-open-v3_e8_s4_v4500-sg$L-s51.json"); done
for L in 0 0.1 0.3; do args+=("drawer-open s5=$D/drawer-open-v3-drawer-open-v3_e8_s5_v4500_tracked-sg$L-s51.json"); done
for L in 0 0.3; do
  args+=("button-press s5, inpaint_start=$D/button-press-v3-button-press-v3_e4_s5_v4500_tracked-inpaint-sg$L-s51.json"); done
python3 $S/sweep_rows.py "${args[@]}"
echo
# 2. the flows: lambda = 0 (sessions 49-50's readings) beside lambda = 0.3 (readers_s51); metrics.json copied from
# each run directory into readers_s51/runs/
A=bench/results/readers_s51; M=$A/runs; B=bench/results/readers_s50
args=()
for s in 4 5 6 7 8; do
  args+=("button-press s$s, λ 0=$M/button-press-v3_e4_s${s}_v4500_tracked=$B/button-press-v3_e4_s${s}_v4500.json")
  args+=("button-press s$s, λ 0.3=$M/button-press-v3_e4_s${s}_v4500_tracked_sg0.3=$A/button-press-v3_e4_s${s}_v4500_tracked_sg0.3.json")
done
f=$A/button-press-v3_e4_s4_v4500_tracked_sg0.1.json
[ -f $f ] && args+=("button-press s4, λ 0.1=$M/button-press-v3_e4_s4_v4500_tracked_sg0.1=$f")
args+=("button-press s4, λ 0.3, inpaint_start, relabelled BC=$M/button-press-v3_e4_s4_v4500_tracked_sg0.3_inpaint_relabel=$A/button-press-v3_e4_s4_v4500_tracked_sg0.3_inpaint.json")
args+=("drawer-open s4, λ 0=$M/drawer-open-v3_e8_s4_v4500=$B/drawer-open-v3_e8_s4_v4500.json")
args+=("drawer-open s4, λ 0.3=$M/drawer-open-v3_e8_s4_v4500_sg0.3=$A/drawer-open-v3_e8_s4_v4500_sg0.3.json")
args+=("sweep-into s4, λ 0=$M/sweep-into-v3_e8_s4_v4500=bench/results/readers_s49/sweep-into-v3_e8_s4_v4500.json")
args+=("sweep-into s4, λ 0.3=$M/sweep-into-v3_e8_s4_v4500_sg0.3=$A/sweep-into-v3_e8_s4_v4500_sg0.3.json")
python3 $S/sg_rows.py "${args[@]}"
