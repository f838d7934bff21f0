#!/usr/bin/env bash
# What the bake cache saves: the table of docs/performance.md ("Re-bakes
# with the cache"). Per world, medians of RUNS runs of the release build
# under /usr/bin/time -v (wall seconds, peak RSS):
#   no cache      bake --no-cache --dry-run of the world as generated
#   empty cache   the same with a cleared cache (a first bake)
#   nothing       bake in place after a full bake, nothing changed
#   moved         bake in place after one instance moved 5 m in one chunk
#   terrain       bake in place after one chunk's terrain raised 2 m
# and the cache's size against the world's own (bytes of its files, and
# blocks on disk).
#
#   benches/cache-edits.sh            # RUNS=3 WORLDS="bench chunks30" WORK=target/cache-edits
#   WORLDS=chunks96 RUNS=1 benches/cache-edits.sh
# Worlds: `bench` (gen --preset bench), `chunksN` (gen --chunks N: bench
# density, N×N chunks; chunks30 is bench tiled 3×3).
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${RUNS:-3}
WORLDS=${WORLDS:-bench chunks30}
WORK=${WORK:-target/cache-edits}
BIN=$(realpath target/release/shadowcull)
cargo build --release --quiet
mkdir -p "$WORK"
WORK=$(realpath "$WORK")

# Edits of a world's files: move an instance, raise a chunk's terrain.
edit() { # edit move|raise FILE AMOUNT
  python3 - "$@" <<'PY'
import io, struct, sys, zipfile, zlib

def move(path, metres):
    text = open(path).read()
    start = text.index("<row3>\t") + len("<row3>\t")
    end = text.index("\t", start)
    x, y, z = (float(v) for v in text[start:end].split())
    row = "%.6f %.6f %.6f" % (x + metres, y, z)
    open(path, "w").write(text[:start] + row + text[end:])

def unfilter(raw, width, height, bpp=4):
    stride = width * bpp
    rows, prev, at = [], bytearray(stride), 0
    for _ in range(height):
        kind, line = raw[at], bytearray(raw[at + 1:at + 1 + stride])
        at += 1 + stride
        for i in range(stride):
            a = line[i - bpp] if i >= bpp else 0
            b, c = prev[i], prev[i - bpp] if i >= bpp else 0
            if kind == 1: line[i] = (line[i] + a) & 255
            elif kind == 2: line[i] = (line[i] + b) & 255
            elif kind == 3: line[i] = (line[i] + (a + b) // 2) & 255
            elif kind == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                line[i] = (line[i] + pred) & 255
        rows.append(line)
        prev = line
    return rows

def chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

def raise_heights(data, metres):
    header, magic, png = data[:32], data[32:36], data[36:]
    at, idat, width, height = 8, b"", 0, 0
    while at < len(png):
        (n,) = struct.unpack(">I", png[at:at + 4])
        kind, body = png[at + 4:at + 8], png[at + 8:at + 8 + n]
        if kind == b"IHDR":
            width, height = struct.unpack(">II", body[:8])
        elif kind == b"IDAT":
            idat += body
        at += 12 + n
    rows = unfilter(zlib.decompress(idat), width, height)
    out, low, high = b"", None, None
    for line in rows:
        values = [v + round(metres * 1000) for v in struct.unpack("<%di" % width, bytes(line))]
        low = min(values + ([low] if low is not None else []))
        high = max(values + ([high] if high is not None else []))
        out += b"\0" + struct.pack("<%di" % width, *values)
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(out)) + chunk(b"IEND", b"")
    header = header[:20] + struct.pack("<ff", low / 1000, high / 1000) + header[28:]
    return header + magic + png

def raise_terrain(path, metres):
    old = zipfile.ZipFile(path)
    items = [(info, old.read(info.filename)) for info in old.infolist()]
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as new:
        for info, data in items:
            if info.filename == "terrain2/heights":
                data = raise_heights(data, metres)
            new.writestr(info, data)
    open(path, "wb").write(buffer.getvalue())

what, path, amount = sys.argv[1], sys.argv[2], float(sys.argv[3])
{"move": move, "raise": raise_terrain}[what](path, amount)
PY
}

# Wall seconds and peak RSS (MB) of one run of the binary.
timed() {
  /usr/bin/time -v "$BIN" "$@" >/dev/null 2>"$WORK/time.txt" || { cat "$WORK/time.txt"; exit 1; }
  local wall rss
  wall=$(awk -F': ' '/Elapsed \(wall clock\)/ {n = split($2, t, ":"); s = 0; for (i = 1; i <= n; i++) s = s * 60 + t[i]; print s}' "$WORK/time.txt")
  rss=$(awk -F': ' '/Maximum resident/ {printf "%.0f", $2 / 1024}' "$WORK/time.txt")
  echo "$wall $rss"
}

median() { sort -n | awk '{v[NR] = $1} END {print v[int((NR + 1) / 2)]}'; }

row() { # row LABEL FILE-OF-"wall rss"-LINES
  local wall rss
  wall=$(cut -d' ' -f1 "$2" | median)
  rss=$(cut -d' ' -f2 "$2" | median)
  printf '| %s | %s | %s |\n' "$1" "$wall" "$rss"
}

for world in $WORLDS; do
  dir="$WORK/$world"
  if [ ! -f "$dir/bake.xml" ]; then
    case $world in
      bench) "$BIN" gen "$dir" --preset bench >/dev/null ;;
      chunks*) "$BIN" gen "$dir" --chunks "${world#chunks}" >/dev/null ;;
      *) echo "unknown world $world" >&2; exit 2 ;;
    esac
  fi
  settings="$dir/bake.xml"
  cache="$WORK/$world-cache"
  space=$(find "$dir/spaces" -mindepth 1 -maxdepth 1 -type d | head -1)
  chunk=$(ls "$space"/*.chunk | sort | sed -n "$(( $(ls "$space"/*.chunk | wc -l) / 2 + 1 ))p")
  cdata="${chunk%.chunk}.cdata"
  rm -f "$WORK"/*.runs
  # A pristine copy to restore: the first rows bake the world as generated.
  rm -rf "$WORK/$world-pristine" && cp -r "$dir" "$WORK/$world-pristine"
  for run in $(seq "$RUNS"); do
    timed bake "$settings" --no-cache --dry-run --quiet --threads 2 >>"$WORK/nocache.runs"
    "$BIN" cache "$cache" clear >/dev/null
    timed bake "$settings" --cache "$cache" --dry-run --quiet --threads 2 >>"$WORK/empty.runs"
  done
  "$BIN" bake "$settings" --cache "$cache" --quiet --threads 2 >/dev/null
  for run in $(seq "$RUNS"); do
    timed bake "$settings" --cache "$cache" --quiet --threads 2 >>"$WORK/nothing.runs"
    sign=$(( run % 2 ? 1 : -1 ))
    edit move "$chunk" $(( 5 * sign ))
    timed bake "$settings" --cache "$cache" --quiet --threads 2 >>"$WORK/moved.runs"
    edit raise "$cdata" $(( 2 * sign ))
    timed bake "$settings" --cache "$cache" --quiet --threads 2 >>"$WORK/terrain.runs"
  done
  world_bytes=$(find "$dir" -type f -not -path '*/.shadowcull-cache/*' -printf '%s\n' | awk '{s += $1} END {print s}')
  cache_bytes=$("$BIN" cache "$cache" stats --json | python3 -c 'import json, sys; print(json.load(sys.stdin)["bytes"])')
  cache_blocks=$(du -sk "$cache" | cut -f1)
  echo
  echo "### $world ($(ls "$space"/*.chunk | wc -l) chunks; edits in $(basename "$chunk"))"
  echo
  echo "| bake | wall s | peak RSS MB |"
  echo "|---|---|---|"
  row "no cache (\`--no-cache --dry-run\`)" "$WORK/nocache.runs"
  row "empty cache (\`--dry-run\`)" "$WORK/empty.runs"
  row "in place, nothing changed" "$WORK/nothing.runs"
  row "in place, one instance moved 5 m" "$WORK/moved.runs"
  row "in place, one chunk's terrain raised 2 m" "$WORK/terrain.runs"
  echo
  echo "world $((world_bytes / 1000)) kB in its files; cache $((cache_bytes / 1000)) kB in its entries ($(( 100 * cache_bytes / world_bytes )) %), $cache_blocks KiB on disk with its folders ($(( 100 * cache_blocks * 1024 / world_bytes )) %)"
  "$BIN" cache "$cache" stats
  rm -rf "$dir" && mv "$WORK/$world-pristine" "$dir"
done
