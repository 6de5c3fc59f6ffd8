#!/usr/bin/env bash
# Download TUM RGB-D benchmark sequences (Sturm et al., IROS 2012) and check them.
#
# Usage: data_scripts/tum.sh [-o DIR] [--archive FILE.tgz] [--checksum HASH] [--dry-run] NAME...
#   NAME     fr1_xyz, freiburg1_xyz or rgbd_dataset_freiburg1_xyz (any TUM RGB-D sequence;
#            default: fr1_xyz fr1_desk fr2_xyz fr3_long_office_household)
#   -o DIR   where to put the sequences (default: data/tum); each lands in
#            DIR/rgbd_dataset_freiburgN_NAME/ with rgb.txt, rgb/, groundtruth.txt, ...
#   --archive FILE   use an already downloaded .tgz instead of fetching (one NAME)
#   --checksum HASH  md5 or sha256 the archive must have (one NAME)
#   --dry-run        print what would be fetched, fetch nothing
#
# Downloads are resumable (run again after an interruption). TUM publishes no checksums,
# so each archive is checked with gzip -t / tar -t, its sha256 is recorded in
# DIR/SHA256SUMS for later runs, and after extraction the number of images in rgb/ must
# equal the number of lines of rgb.txt.
# Read with: open_sequence("tum", "DIR/rgbd_dataset_freiburg1_xyz") (camera from the name).
set -o errexit -o nounset -o pipefail
# shellcheck source=SCRIPTDIR/common.sh
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"

BASE_URL=${TUM_BASE_URL:-https://cvg.cit.tum.de/rgbd/dataset}
DEST=data/tum
ARCHIVE=""
CHECKSUM=""
NAMES=()

while [[ $# -gt 0 ]]; do
    case $1 in
        -o | --output) DEST=${2:?-o needs a folder}; shift 2 ;;
        --archive) ARCHIVE=${2:?--archive needs a file}; shift 2 ;;
        --checksum) CHECKSUM=${2:?--checksum needs a hash}; shift 2 ;;
        --dry-run) DRY_RUN=1; shift ;;
        -h | --help) usage 0 ;;
        -*) log "unknown option $1"; usage 2 ;;
        *) NAMES+=("$1"); shift ;;
    esac
done
[[ ${#NAMES[@]} -gt 0 ]] || NAMES=(fr1_xyz fr1_desk fr2_xyz fr3_long_office_household)
if [[ -n "$ARCHIVE$CHECKSUM" && ${#NAMES[@]} -ne 1 ]]; then
    die "--archive and --checksum apply to exactly one sequence NAME"
fi
need tar gzip sha256sum find

# canonical NAME: set GROUP=freiburgN and SEQ=rgbd_dataset_freiburgN_rest, or die.
canonical() {
    local n=${1#rgbd_dataset_}
    [[ $n =~ ^(fr|freiburg)([123])_([A-Za-z0-9_]+)$ ]] \
        || die "'$1' is not a TUM RGB-D sequence name (expected e.g. fr1_xyz or rgbd_dataset_freiburg3_long_office_household)"
    GROUP=freiburg${BASH_REMATCH[2]}
    SEQ=rgbd_dataset_freiburg${BASH_REMATCH[2]}_${BASH_REMATCH[3]}
}
for name in "${NAMES[@]}"; do canonical "$name"; done  # reject a bad name before any download

for name in "${NAMES[@]}"; do
    canonical "$name"
    group=$GROUP seq=$SEQ
    archive=${ARCHIVE:-$DEST/$seq.tgz}
    if [[ -z "$ARCHIVE" ]]; then
        fetch "$BASE_URL/$group/$seq.tgz" "$archive"
    fi
    verify_archive "$archive"
    expect_hash "$archive" "$CHECKSUM"
    if [[ -f "$DEST/$seq/.complete" ]]; then
        log "$seq already extracted in $DEST/$seq"
        continue
    fi
    log "extracting $(basename "$archive") into $DEST"
    run mkdir -p "$DEST"
    run tar -xzf "$archive" -C "$DEST"
    [[ "$DRY_RUN" == 1 ]] && continue
    [[ -f "$DEST/$seq/rgb.txt" ]] || die "$DEST/$seq/rgb.txt missing after extraction: not a TUM RGB-D archive?"
    expect_count "$seq/rgb" "$(count_files "$DEST/$seq/rgb" '*.png')" "$(data_lines "$DEST/$seq/rgb.txt")"
    if [[ -f "$DEST/$seq/depth.txt" ]]; then
        expect_count "$seq/depth" "$(count_files "$DEST/$seq/depth" '*.png')" "$(data_lines "$DEST/$seq/depth.txt")"
    fi
    [[ -f "$DEST/$seq/groundtruth.txt" ]] || log "note: $seq has no groundtruth.txt (a validation/test sequence)"
    touch "$DEST/$seq/.complete"
    log "ready: $DEST/$seq"
done
