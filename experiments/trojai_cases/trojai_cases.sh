#!/usr/bin/env bash
# Issue 31's numbered cases, rerun on TrojAI's example files (cache of experiments/trojai_examples/trojai_examples.py)
# and tiny Randomized LavaWorld models trained here (9x9 rooms, 1 and 3 lava squares):
#   bash experiments/trojai_cases/trojai_cases.sh [WORK_FOLDER] > experiments/trojai_cases/trojai_cases.txt
set -u
cd "$(dirname "$0")/../.."
R=.venv/bin/rlbackdoors; C=~/.cache/rlbackdoors/trojai-example; T="${1:-/tmp/trojai-cases}"; mkdir -p "$T"; rm -rf $T/det1 $T/det3 $T/s $T/out.txt $T/beh
[ -d $T/rlw1 ] || .venv/bin/python experiments/trojai_cases/trojai_cases_models.py $T/rlw1 1 cells:0,0
[ -d $T/rlw3 ] || .venv/bin/python experiments/trojai_cases/trojai_cases_models.py $T/rlw3 3 "cells:0,0;1,1;2,2"
AUG=$C/rl-randomized-lavaworld-aug2023/model/id-00000000
CM=$C/rl-colorful-memory-sep2024/model/rl-colorful-memory-sep2024-example
SG=$C/rl-safetygymnasium-oct2024/model/rl-safetygymnasium-oct2024-example
JUL=$C/rl-lavaworld-jul2023@d969b25/model/rl-lavaworld-jul2023-example
$R detect fit --detector weights --zoo $T/rlw1 --out $T/det1 --param min_per_class=1 --quiet
$R detect fit --detector weights --zoo $T/rlw3 --out $T/det3 --param min_per_class=1 --quiet
inf() { m=$1; det=$2; meta=$3; shift 3; $R detect infer --model_filepath $m/model.pt --result_filepath $T/out.txt --scratch_dirpath $T/s --round_training_dataset_dirpath $T --metaparameters_filepath $meta/metaparameters.json --schema_filepath $meta/metaparameters_schema.json --learned_parameters_dirpath $det "$@"; echo "rc=$? result=$(cat $T/out.txt 2>/dev/null)"; rm -f $T/out.txt; }
echo "== case 1: Aug 2023 example (config.json only), detector fitted on 9x9 one-lava models"; inf $AUG $T/det1 $T/det1
echo "== case 2: statistics=false against a detector fitted with true"; mkdir -p $T/m2; python3 -c "
import json; d=json.load(open('$T/det1/metaparameters.json')); d['statistics']=False; json.dump(d, open('$T/m2/metaparameters.json','w'))"; cp $T/det1/metaparameters_schema.json $T/m2/; inf $AUG $T/det1 $T/m2; inf $AUG $T/det1 $T/m2 --allow-mismatch
echo "== case 3: top_k=-5"; mkdir -p $T/m3; python3 -c "
import json; d=json.load(open('$T/det1/metaparameters.json')); d['top_k']=-5; json.dump(d, open('$T/m3/metaparameters.json','w'))"; cp $T/det1/metaparameters_schema.json $T/m3/; inf $AUG $T/det1 $T/m3
echo "== case 4: a Randomized LavaWorld detector on the Colorful Memory, Safety and LavaWorld examples"; inf $CM $T/det1 $T/det1; inf $SG $T/det1 $T/det1; inf $JUL $T/det1 $T/det1
echo "== case 4b: fitted on 9x9 three-lava models, the 9x9 one-lava example"; inf $AUG $T/det3 $T/det3
echo "== case 5: behaviour on the Aug 2023 setting"; $R detect fit --detector behaviour --zoo $T/rlw1 --out $T/beh --quiet; echo "rc=$? exists=$(test -e $T/beh && echo yes || echo no)"
echo "== case 6, 7: import with no flags"; for m in $AUG $JUL; do rm -rf $T/imp; $R zoo import-trojai $m --out $T/imp --episodes 200 --policy greedy; python3 -c "
import json; c=json.load(open('$T/imp/models/id-00000000/config.json'))['env']; t=json.load(open('$T/imp/models/id-00000000/trojai.json')); m=json.load(open('$T/imp/models/id-00000000/metrics.json')); print(c, t['env_sources'], 'clean SR', m['clean_sr'])"; done
echo "== case 8: evaluate --weights on a file that is not a zip"; echo garbage > $T/g.pt; $R evaluate --weights $T/g.pt; echo "rc=$?"
echo "== case 9: a raw-pickle model.pt"; python3 -c "import pickle; open('$T/raw.pt','wb').write(pickle.dumps({'a': [1]}, protocol=4))"; $R evaluate --weights $T/raw.pt --env lavaworld --arch fc; echo "rc=$?"
