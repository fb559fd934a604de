#!/usr/bin/env bash
# Is a refactor behaviour-preserving? Flies the default, wide and team missions and evaluates Table II (paper split)
# and a small Table III on one checkout, then compares two such runs file by file.
#
#   tools/behaviour_check.sh run CHECKOUT OUT [CACHE_DIR]   # CHECKOUT has its own .venv (e.g. a git worktree of the old commit)
#   tools/behaviour_check.sh compare BEFORE_OUT AFTER_OUT
#
# `compare` exits 1 when a flight or a table differs (the tables' .md files differ only in their wall-time line).
set -uo pipefail
case "${1:-}" in
run)
  root=$2; out=$(realpath -m "$3"); cache=${4:-$out/cache}; mkdir -p "$out"
  u() { (cd "$root" && .venv/bin/python -m uavsearch "$@"); }
  u fly --out "$out/fly_default" > "$out/fly_default.txt" 2>&1
  u fly --mission missions/wide.yaml --out "$out/fly_wide" > "$out/fly_wide.txt" 2>&1
  u fly --mission missions/wide_team.yaml --out "$out/fly_team" > "$out/fly_team.txt" 2>&1
  u eval search --setting all --split paper --out "$out/eval_paper" --cache-dir "$cache" --progress false \
    > "$out/eval_paper.txt" 2>&1
  u eval search --setting wide --wide-train-scenes 20 --wide-val-scenes 5 --wide-test-scenes 10 --seeds 1 \
    --bounds false --out "$out/eval_wide" --cache-dir "$cache" --progress false > "$out/eval_wide.txt" 2>&1
  ;;
compare)
  before=$2; after=$3; here=$(dirname "$0"); rc=0
  for f in fly_default fly_wide fly_team; do
    echo "== $f"
    python3 "$here/compare_flights.py" "$before/$f" "$after/$f" --ignore mission_file --ignore tlog_clock | tail -1 || rc=1
    for v in "$before/$f"/vehicle*/; do
      [ -d "$v" ] && { diff -rq "$v/images" "$after/$f/$(basename "$v")/images" > /dev/null \
        && echo "$(basename "$v") images the same" || { echo "$(basename "$v") images DIFFER"; rc=1; }; }
    done
  done
  for d in eval_paper eval_wide; do
    echo "== $d"
    for f in "$before/$d"/*.csv "$before/$d"/*.png; do
      cmp -s "$f" "$after/$d/$(basename "$f")" && echo "same $(basename "$f")" || { echo "DIFFERS $(basename "$f")"; rc=1; }
    done
  done
  exit $rc
  ;;
*) echo "usage: tools/behaviour_check.sh run CHECKOUT OUT [CACHE_DIR] | compare BEFORE_OUT AFTER_OUT" >&2; exit 2 ;;
esac
