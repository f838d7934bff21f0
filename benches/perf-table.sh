#!/usr/bin/env bash
# Reproduces the tables of docs/performance.md: generates the worlds, then
# runs `shadowcull bake SETTINGS --dry-run --quiet --no-cache [OPTIONS]` RUNS times for
# every row, the rows taking turns run after run so that a change in the
# machine's load touches every row alike, and prints one Markdown table per
# world: median wall seconds (with the range), the lights' rays and trace
# seconds from the bake's closing table, and the median peak resident
# memory from /usr/bin/time -v.
#
#   benches/perf-table.sh [WORK_DIR]          (default: target/perf)
#
# Environment: SHADOWCULL (the binary; default: `cargo build --release`,
# then target/release/shadowcull), RUNS (default 5), CHUNKS (the side of the
# generated `gen --chunks N` world, default 20), THREADS (default: one per
# core), TABLES_ONLY=1 (print the tables of the last run in WORK_DIR again,
# without measuring). Nothing outside WORK_DIR is written; the bundled
# village is baked with --dry-run in place.
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
work=$(realpath -m "${1:-$repo/target/perf}")
runs=${RUNS:-5}
chunks=${CHUNKS:-20}
threads=${THREADS:-$(nproc)}

if [ -z "${SHADOWCULL:-}" ]; then
  (cd "$repo" && cargo build --release --quiet)
  SHADOWCULL=$repo/target/release/shadowcull
fi
bin=$(realpath "$SHADOWCULL")
[ -x /usr/bin/time ] || { echo "perf-table: needs GNU time at /usr/bin/time (apt-get install time)" >&2; exit 1; }

mkdir -p "$work"
log() { echo "perf-table: $*" >&2; }

# The worlds: the village fixture as committed, the bench preset and an
# N×N-chunk world generated, each with the committed settings variants
# beside its bake.xml (their paths are relative to the settings file).
village=$repo/fixtures/worlds/village
bench=$work/bench
big=$work/chunks$chunks
if [ ! -f "$bench/bake.xml" ]; then
  log "generating bench"
  "$bin" gen "$bench" --preset bench >/dev/null
fi
if [ ! -f "$big/bake.xml" ]; then
  log "generating a ${chunks}×${chunks}-chunk world"
  "$bin" gen "$big" --chunks "$chunks" >/dev/null
fi
cp "$repo"/benches/settings/sun-0.25.xml "$repo"/benches/settings/persp.xml "$bench"/
cp "$repo"/benches/settings/sun-0.25.xml "$big"/

# One row: world label | settings file | options (space-separated).
rows=(
  "village|$village/bake.xml|"
  "village|$village/bake.xml|--refine"
  "village|$village/bake.xml|--conservative"
  "village|$village/bake.xml|--filter-radius 1"
  "bench|$bench/bake.xml|"
  "bench|$bench/bake.xml|--refine"
  "bench|$bench/bake.xml|--conservative"
  "bench|$bench/bake.xml|--filter-radius 1"
  "bench|$bench/sun-0.25.xml|"
  "bench|$bench/persp.xml|"
  "chunks$chunks|$big/bake.xml|"
  "chunks$chunks|$big/sun-0.25.xml|"
)

results=$work/results
if [ -z "${TABLES_ONLY:-}" ]; then
  rm -rf "$results"
  mkdir -p "$results"
fi

# The rays and trace seconds of every light, summed, from the closing table
# the bake prints (a row per light: bit, name, kind, rays, triangles, bvh s,
# trace s, Mrays/s, useful, culled).
light_sums() {
  awk '$1 ~ /^[0-9]+$/ && NF == 10 { rays += $4; trace += $7 } END { printf "%.6f %d\n", trace, rays }' "$1"
}

measure() {
  for run in $(seq "$runs"); do
    for i in "${!rows[@]}"; do
      IFS='|' read -r world settings options <<<"${rows[$i]}"
      log "run $run/$runs: $world $(basename "$settings") $options"
      # shellcheck disable=SC2086
      /usr/bin/time -v -o "$results/$i.time" "$bin" bake "$settings" --dry-run --quiet --no-cache \
        --threads "$threads" $options >"$results/$i.out"
      wall=$(awk -F': ' '/Elapsed \(wall clock\)/ { n = split($2, p, ":"); s = 0; for (k = 1; k <= n; k++) s = s * 60 + p[k]; print s }' "$results/$i.time")
      rss=$(awk -F': ' '/Maximum resident set size/ { print $2 }' "$results/$i.time")
      echo "$wall $rss $(light_sums "$results/$i.out")" >>"$results/$i.runs"
    done
  done
}

if [ -z "${TABLES_ONLY:-}" ]; then
  {
    echo "date=$(date -u +%Y-%m-%d)"
    echo "load_before='$(cut -d' ' -f1-3 /proc/loadavg)'"
  } >"$results/context"
  measure
  echo "load_after='$(cut -d' ' -f1-3 /proc/loadavg)'" >>"$results/context"
fi
# shellcheck disable=SC1091
. "$results/context"

# The median of column $1 of a file, and its least and greatest values.
# (/usr/bin/time reports memory in KiB; the tables give MB, 10^6 bytes.)
median() { awk -v c="$1" '{ print $c }' "$2" | sort -g | awk '{ v[NR] = $1 } END { printf "%s %s %s\n", v[int((NR + 1) / 2)], v[1], v[NR] }'; }

{
  echo "Measured $date on $(nproc) cores ($(sed -n 's/^model name\s*: //p' /proc/cpuinfo | head -n1)), $(awk '/MemTotal/ { printf "%.0f GiB", $2 / 1048576 }' /proc/meminfo);"
  echo "$("$bin" --version), --threads $threads, median of $runs runs (range in brackets);"
  echo "load average before $load_before, after $load_after."
  current=""
  for i in "${!rows[@]}"; do
    IFS='|' read -r world settings options <<<"${rows[$i]}"
    if [ "$world" != "$current" ]; then
      current=$world
      stats=$("$bin" inspect "$settings" --json | python3 -c 'import json, sys; w = json.load(sys.stdin); print(", ".join("%d %s" % (w[k], k) for k in ("chunks", "instances", "triangles")))')
      echo
      echo "### $world ($stats)"
      echo
      echo "| settings | options | rays | wall s | trace s | Mrays/s | peak RSS |"
      echo "|---|---|---|---|---|---|---|"
    fi
    read -r wall lo hi < <(median 1 "$results/$i.runs")
    read -r rss _ _ < <(median 2 "$results/$i.runs")
    read -r trace _ _ < <(median 3 "$results/$i.runs")
    read -r rays _ _ < <(median 4 "$results/$i.runs")
    awk -v s="$(basename "$settings")" -v o="${options:-}" -v r="$rays" -v w="$wall" -v lo="$lo" -v hi="$hi" \
      -v t="$trace" -v m="$rss" 'BEGIN {
        printf "| `%s` | %s | %.1f M | %.2f (%.2f–%.2f) | %.2f | %.1f | %.0f MB |\n",
          s, (o == "" ? "—" : "`" o "`"), r / 1e6, w, lo, hi, t, (t > 0 ? r / t / 1e6 : 0), m * 1024 / 1e6
      }'
  done
} | tee "$work/perf-table.md"
log "tables written to $work/perf-table.md"
