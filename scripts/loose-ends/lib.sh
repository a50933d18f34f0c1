# Case helpers for scripts/loose-ends.sh. Each case runs one command in a fresh folder ($CASE, also its cwd).
#   refuse NAME PATTERN -- COMMAND...   must exit non-zero with no traceback and exactly one error line on
#                                       stderr ("s3k CMD: error: ...", notes and warnings may come before it), and
#                                       that line must match PATTERN (grep -E, case-insensitive)
#   accept NAME CHECK -- COMMAND...     must exit 0, then the shell snippet CHECK (run in $CASE) must succeed
# Set-up shared by an area's cases goes in a function the area calls first; $LOOSE_WORK is a scratch folder
# kept for the whole run.
LOOSE_WORK=${LOOSE_WORK:-$(mktemp -d)}
LOOSE_PASS=0
LOOSE_FAIL=0
_loose_run() {  # runs "$@" in a new case folder, leaving $CASE, $rc, $out, $err
    CASE=$(mktemp -d "$LOOSE_WORK/case.XXXX")
    out="$CASE/.stdout"; err="$CASE/.stderr"
    (cd "$CASE" && "$@" >"$out" 2>"$err" </dev/null); rc=$?
}
_loose_verdict() {  # NAME OK WHY
    if [ "$2" = 1 ]; then LOOSE_PASS=$((LOOSE_PASS + 1)); printf '  ok    %s: %s\n' "$1" "$3"
    else LOOSE_FAIL=$((LOOSE_FAIL + 1)); printf '  FAIL  %s: %s\n' "$1" "$3"; fi
}
refuse() {
    local name=$1 pattern=$2; shift 3
    _loose_run "$@"
    local lines; lines=$(grep -cE '(^|: )error: ' "$err")
    local line; line=$(grep -E '(^|: )error: ' "$err" | head -n 1)
    if [ $rc -ne 0 ] && [ "$lines" = 1 ] && ! grep -q Traceback "$err" && grep -qiE -- "$pattern" <<<"$line"; then
        _loose_verdict "$name" 1 "refused: $line"
    else
        _loose_verdict "$name" 0 "rc=$rc, $lines error lines: $(head -c 400 "$err" | tr '\n' ' ')"
    fi
}
accept() {
    local name=$1 check=$2; shift 3
    _loose_run "$@"
    if [ $rc -eq 0 ] && (cd "$CASE" && eval "$check") >/dev/null 2>&1; then
        _loose_verdict "$name" 1 "done as it should ($(grep -m1 . "$err" | head -c 200))"
    else
        _loose_verdict "$name" 0 "rc=$rc or check '$check' failed: $(head -c 400 "$err" | tr '\n' ' ')"
    fi
}
summary() {
    echo "$LOOSE_PASS passed, $LOOSE_FAIL failed"
    [ "$LOOSE_FAIL" = 0 ]
}
