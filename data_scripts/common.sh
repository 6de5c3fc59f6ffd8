# shellcheck shell=bash
# Helpers shared by the download scripts in this folder; sourced, never run on its own.
#
# fetch:   resumable download (curl -C - or wget -c) into NAME.part, renamed when complete,
#          so an interrupted run continues where it stopped and a finished file is kept.
# verify:  archive integrity (unzip -t, gzip -t + tar -t) and sha256 bookkeeping: after a
#          first successful check the archive's sha256 is recorded in SHA256SUMS next to it,
#          and later runs check against that record.

set -o errexit -o nounset -o pipefail

DRY_RUN=${DRY_RUN:-0}

log() { printf '[%s] %s\n' "$(basename "$0")" "$*" >&2; }
die() { printf '[%s] error: %s\n' "$(basename "$0")" "$*" >&2; exit 1; }

need() {
    local cmd
    for cmd in "$@"; do
        command -v "$cmd" >/dev/null 2>&1 || die "'$cmd' is required but not installed"
    done
}

# usage [STATUS]: print the script's header comment (its documentation) and exit.
usage() {
    awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"
    exit "${1:-0}"
}

# run CMD...: execute, or only print it with DRY_RUN=1.
run() {
    if [[ "$DRY_RUN" == 1 ]]; then
        printf '+ %s\n' "$*" >&2
    else
        "$@"
    fi
}

# fetch URL OUT: download URL to OUT, resuming a partial OUT.part. Skips a complete OUT.
fetch() {
    local url=$1 out=$2
    if [[ -s "$out" ]]; then
        log "already downloaded: $out"
        return 0
    fi
    mkdir -p "$(dirname "$out")"
    log "downloading $url"
    if command -v curl >/dev/null 2>&1; then
        run curl --fail --location --retry 5 --retry-delay 10 --continue-at - \
            --output "$out.part" "$url" || fetch_failed "$url" "$out"
    elif command -v wget >/dev/null 2>&1; then
        run wget --continue --tries=5 --waitretry=10 --output-document="$out.part" "$url" \
            || fetch_failed "$url" "$out"
    else
        die "neither curl nor wget is installed"
    fi
    run mv -f "$out.part" "$out"
}

fetch_failed() {
    die "download of $1 failed (partial data kept in $2.part; run again to resume). If the URL has moved, download the file by hand and pass it with --archive"
}

# sha256_check FILE: if SHA256SUMS beside FILE lists it, check it (die on mismatch) and return 0;
# return 1 when there is no record yet.
sha256_check() {
    local file=$1 dir base
    dir=$(dirname "$file")
    base=$(basename "$file")
    [[ -f "$dir/SHA256SUMS" ]] && grep -q "  $base\$" "$dir/SHA256SUMS" || return 1
    log "checking sha256 of $base"
    (cd "$dir" && grep "  $base\$" SHA256SUMS | sha256sum --check --status) \
        || die "$file: sha256 differs from the recorded one in $dir/SHA256SUMS; delete it and download again"
}

sha256_record() {
    local file=$1 dir base
    dir=$(dirname "$file")
    base=$(basename "$file")
    (cd "$dir" && sha256sum "$base" >>SHA256SUMS) 2>/dev/null \
        || log "note: cannot write $dir/SHA256SUMS; the archive will be re-tested next time"
}

# verify_archive FILE: integrity of a .zip / .tgz / .tar.gz / .tar archive.
verify_archive() {
    local file=$1
    [[ "$DRY_RUN" == 1 ]] && { log "(dry run) would verify $file"; return 0; }
    [[ -s "$file" ]] || die "$file: missing or empty"
    if sha256_check "$file"; then
        return 0
    fi
    log "testing archive integrity of $(basename "$file")"
    case "$file" in
        *.zip) unzip -tq "$file" >/dev/null || die "$file: corrupt zip (unzip -t failed); delete it and download again" ;;
        *.tgz | *.tar.gz) { gzip -t "$file" && tar -tzf "$file" >/dev/null; } \
            || die "$file: corrupt archive (gzip -t / tar -t failed); delete it and download again" ;;
        *.tar) tar -tf "$file" >/dev/null || die "$file: corrupt tar archive; delete it and download again" ;;
        *) log "no integrity test for $(basename "$file")"; return 0 ;;
    esac
    sha256_record "$file"
}

# count_files DIR GLOB: number of files matching GLOB directly in DIR.
count_files() {
    find "$1" -maxdepth 1 -type f -name "$2" | wc -l
}

# data_lines FILE: number of non-empty, non-comment lines.
data_lines() {
    grep -cv -e '^[[:space:]]*#' -e '^[[:space:]]*$' "$1" || true
}

# expect_count WHAT GOT WANT: die unless GOT == WANT.
expect_count() {
    [[ "$2" -eq "$3" ]] || die "$1: found $2 files, expected $3 (incomplete download or extraction?)"
    log "$1: $2 files, as expected"
}

# expect_hash FILE HASH: check FILE against a published md5 (32 hex) or sha256 (64 hex).
expect_hash() {
    local file=$1 want=$2 got tool
    [[ -z "$want" || "$DRY_RUN" == 1 ]] && return 0
    case ${#want} in
        32) tool=md5sum ;;
        64) tool=sha256sum ;;
        *) die "checksum '$want' is neither md5 (32 hex digits) nor sha256 (64 hex digits)" ;;
    esac
    log "checking $tool of $(basename "$file")"
    got=$($tool "$file" | cut -d' ' -f1)
    [[ "${got,,}" == "${want,,}" ]] || die "$file: $tool is $got, expected $want; delete it and download again"
}
