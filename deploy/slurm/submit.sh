#!/bin/bash
# Submits a distributed shadowcull bake to Slurm: the shard array, then the
# merge with --dependency=afterok on the whole array. Prints the two job ids
# ("ARRAY_ID MERGE_ID").
#
#   deploy/slurm/submit.sh SETTINGS PARTIALS_DIR ARRAY [OUT_DIR]
#     ARRAY: an sbatch --array range, e.g. 0-63 or 1-7:2 (ids need not start at 0)
#   Environment: SHADOWCULL (the binary, default `shadowcull` on PATH),
#   BAKE_FLAGS (flags for every shard and the merge), MERGE_FLAGS (merge
#   only, e.g. --refine), REPORT (merge report file), SBATCH_FLAGS (extra
#   sbatch options for both jobs, e.g. "--partition=bake --time=2:00:00"),
#   CACHE (the bake cache the jobs share, default PARTIALS_DIR/../shadowcull-cache;
#   `none` for no cache).
set -euo pipefail
if [ $# -lt 3 ]; then
  sed -n '2,14p' "$0" >&2
  exit 2
fi
settings=$(realpath "$1")
partials=$(realpath -m "$2")
array=$3
out=${4:+$(realpath -m "$4")}
here=$(cd "$(dirname "$0")" && pwd)

# The shard count: the number of ids in A-B[:S].
range=${array%%%*}
first=${range%%-*}
rest=${range#*-}
last=${rest%%:*}
step=1
[[ $rest == *:* ]] && step=${rest#*:}
if ! [[ $first =~ ^[0-9]+$ && $last =~ ^[0-9]+$ && $step =~ ^[0-9]+$ ]] || [ "$last" -lt "$first" ] || [ "$step" -lt 1 ]; then
  echo "submit.sh: ARRAY must be a range A-B or A-B:S, got $array" >&2
  exit 2
fi
shards=$(( (last - first) / step + 1 ))
mkdir -p "$partials"

export SETTINGS="$settings" PARTIALS="$partials" SHARDS="$shards" OUT="${out:-}"
# shellcheck disable=SC2086
array_id=$(sbatch --parsable ${SBATCH_FLAGS:-} --array="$array" --chdir="$partials" \
  --export=ALL "$here/shard.sbatch")
array_id=${array_id%%;*}
# shellcheck disable=SC2086
merge_id=$(sbatch --parsable ${SBATCH_FLAGS:-} --dependency=afterok:"$array_id" \
  --kill-on-invalid-dep=yes --chdir="$partials" --export=ALL "$here/merge.sbatch")
merge_id=${merge_id%%;*}
echo "$array_id $merge_id"
