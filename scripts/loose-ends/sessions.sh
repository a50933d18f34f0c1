# Sessions: datasets of several recordings (s3k import --into/--session/--dataset/--manifest, --test-sessions).
sessions_setup() {
    [ -d "$LOOSE_WORK/sessions/a" ] && return
    mkdir -p "$LOOSE_WORK/sessions"
    for seed in 0 1; do
        s3k simulate box --out "$LOOSE_WORK/sessions/s$seed" --size 32 --labelled 2 --unlabelled 2 --test 2 \
            --seed $seed --workers 1 --no-progress >/dev/null 2>&1
    done
    cp -r "$LOOSE_WORK/sessions/s0" "$LOOSE_WORK/sessions/a"
}
sessions_setup
S=$LOOSE_WORK/sessions
with_copy() { cp -r "$S/a" ds && "$@"; }
refuse "a session the dataset holds" "already holds session 'default'" -- \
    with_copy s3k import --into ds --session default --dataset "$S/s1"
refuse "--into without --session" "--session NAME" -- with_copy s3k import --into ds --dataset "$S/s1"
refuse "--dataset without --into" "--into" -- s3k import --out new --session x --dataset "$S/s1"
refuse "a session name that is no file name" "--session" -- \
    with_copy s3k import --into ds --session "../x" --dataset "$S/s1"
refuse "--test-sessions naming another session" "this import's session is 'late'" -- \
    with_copy s3k import --into ds --session late --dataset "$S/s1" --test-sessions early
refuse "a manifest without sessions" "field 'sessions'" -- \
    bash -c 'echo "{}" > m.json && s3k import --manifest m.json --out new'
refuse "a manifest that is not TOML" "not valid TOML" -- \
    bash -c 'echo "[[sessions" > m.toml && s3k import --manifest m.toml --out new'
accept "a dataset added as a session" \
    'grep -q "\"late\"" ds/s3k.json && [ "$(grep -c ",late" ds/frames.csv)" = 6 ]' -- \
    with_copy s3k import --into ds --session late --dataset "$S/s1" --subject box-2
accept "a session held out whole" '[ "$(grep -c "test,late\|,test.*late" ds/frames.csv)" = 4 ]' -- \
    with_copy s3k import --into ds --session late --dataset "$S/s1" --test-sessions late
