#!/usr/bin/env bash
# Fetch loop-closure (place recognition) datasets with hand-labelled ground truth, and check them.
#
# Usage: data_scripts/placerec.sh [-o DIR] [--archive FILE] [--checksum HASH] [--dry-run] NAME...
#   NAME  newcollege   New College, Oxford (Cummins & Newman, FAB-MAP, IJRR 2008): 2146 images
#         citycentre   City Centre, Oxford (same paper): 2474 images
#         lip6indoor   Lip6 Indoor, Paris (Angeli et al., IEEE T-RO 2008): 388 images
#         lip6outdoor  Lip6 Outdoor, Paris (same paper): 1063 images
#         stlucia      St Lucia, Brisbane (Glover et al., ICRA 2010)
#   -o DIR            destination (default: data/placerec); each lands in DIR/NAME/
#   --archive FILE    an image archive (zip or tar) you downloaded by hand, for one NAME
#   --checksum HASH   md5 or sha256 the archive must have
#   --dry-run         print what would be done
#
# New College and City Centre are fetched from Oxford's FAB-MAP data page
#   https://www.robots.ox.ac.uk/~mobile/IJRR_2008_Dataset/data.html
# (images as Images.zip, ground truth as masks/<Name>GroundTruth.mat: a matrix whose (i, j)
# entry is 1 where images i and j show the same place; the images alternate left and right
# camera). Links as known when this script was written; override with NEWCOLLEGE_URL /
# CITYCENTRE_URL and NEWCOLLEGE_GT_URL / CITYCENTRE_GT_URL, or download by hand and pass
# --archive, if they move.
# Lip6 and St Lucia have no stable direct link: the script prints where to get them and
# what to pass back with --archive.
#
# Each archive is tested (unzip -t / tar -t, sha256 recorded in SHA256SUMS beside it) and,
# where the published image count is known, the unpacked images are counted.
set -o errexit -o nounset -o pipefail
# shellcheck source=SCRIPTDIR/common.sh
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"

OX=https://www.robots.ox.ac.uk/~mobile/IJRR_2008_Dataset/Data
declare -A URL=(
    [newcollege]=${NEWCOLLEGE_URL:-$OX/NewCollege/Images.zip}
    [citycentre]=${CITYCENTRE_URL:-$OX/CityCentre/Images.zip}
)
declare -A GT_URL=(
    [newcollege]=${NEWCOLLEGE_GT_URL:-$OX/NewCollege/masks/NewCollegeGroundTruth.mat}
    [citycentre]=${CITYCENTRE_GT_URL:-$OX/CityCentre/masks/CityCentreGroundTruth.mat}
)
declare -A COUNT=([newcollege]=2146 [citycentre]=2474 [lip6indoor]=388 [lip6outdoor]=1063)
declare -A MANUAL=(
    [lip6indoor]="Lip6 Indoor (Angeli, Filliat, Doncieux, Meyer, IEEE T-RO 24(5), 2008):
    open http://cogrob.ensta-paris.fr/loopclosure.html (formerly cogrob.ensta-paristech.fr),
    download the Lip6 Indoor data set archive (images and Lip6IndoorGroundTruth.mat), then run
      data_scripts/placerec.sh --archive <the archive> lip6indoor"
    [lip6outdoor]="Lip6 Outdoor (Angeli, Filliat, Doncieux, Meyer, IEEE T-RO 24(5), 2008):
    open http://cogrob.ensta-paris.fr/loopclosure.html (formerly cogrob.ensta-paristech.fr),
    download the Lip6 Outdoor data set archive (images and Lip6OutdoorGroundTruth.mat), then run
      data_scripts/placerec.sh --archive <the archive> lip6outdoor"
    [stlucia]="St Lucia (Glover, Maddern, Milford, Wyeth, 'FAB-MAP + RatSLAM: appearance-based
    SLAM for multiple times of day', ICRA 2010), recorded by QUT around the University of
    Queensland's St Lucia campus: search for 'St Lucia Multiple Times of Day' on QUT's
    research data pages (formerly https://wiki.qut.edu.au/display/cyphy/St+Lucia+Multiple+Times+of+Day),
    download one run's image archive, then run
      data_scripts/placerec.sh --archive <the archive> stlucia"
)

DEST=data/placerec
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
        *) NAMES+=("${1,,}"); shift ;;
    esac
done
[[ ${#NAMES[@]} -gt 0 ]] || { log "name at least one data set"; usage 2; }
for n in "${NAMES[@]}"; do
    [[ -n "${URL[$n]:-}${MANUAL[$n]:-}" ]] || die "unknown data set '$n'; one of: newcollege citycentre lip6indoor lip6outdoor stlucia"
done
if [[ -n "$ARCHIVE$CHECKSUM" && ${#NAMES[@]} -ne 1 ]]; then
    die "--archive and --checksum apply to exactly one NAME"
fi
[[ -z "$ARCHIVE" || -f "$ARCHIVE" ]] || die "$ARCHIVE: file not found"
need unzip tar sha256sum find

# unpack ARCHIVE OUT: extract a zip or tar archive into OUT.
unpack() {
    run mkdir -p "$2"
    log "unpacking $(basename "$1") into $2"
    case $1 in
        *.zip) run unzip -q -o "$1" -d "$2" ;;
        *.tar | *.tgz | *.tar.gz | *.tar.bz2 | *.tbz2 | *.tar.xz) run tar -xf "$1" -C "$2" ;;
        *) die "$1: unknown archive type (expected zip or tar)" ;;
    esac
}

status=0
for n in "${NAMES[@]}"; do
    out=$DEST/$n
    if [[ -f "$out/.complete" ]]; then
        log "$n already in $out"
        continue
    fi
    archive=$ARCHIVE
    if [[ -z "$archive" ]]; then
        if [[ -z "${URL[$n]:-}" ]]; then
            printf '\n%s needs manual steps:\n    %s\n\n' "$n" "${MANUAL[$n]}" >&2
            status=3
            continue
        fi
        archive=$DEST/downloads/$n-$(basename "${URL[$n]}")
        fetch "${URL[$n]}" "$archive"
    fi
    verify_archive "$archive"
    expect_hash "$archive" "$CHECKSUM"
    unpack "$archive" "$out"
    if [[ -n "${GT_URL[$n]:-}" ]]; then
        fetch "${GT_URL[$n]}" "$out/$(basename "${GT_URL[$n]}")"
    fi
    [[ "$DRY_RUN" == 1 ]] && continue
    images=$(find "$out" -type f \( -iname '*.jpg' -o -iname '*.jpeg' -o -iname '*.png' -o -iname '*.ppm' -o -iname '*.pgm' -o -iname '*.bmp' \) | wc -l)
    [[ "$images" -gt 0 ]] || die "$out: no images after unpacking $archive"
    if [[ -n "${COUNT[$n]:-}" ]]; then
        expect_count "$n images" "$images" "${COUNT[$n]}"
    else
        log "$n: $images images (no published count to check against)"
    fi
    gt=$(find "$out" -maxdepth 3 -iname '*groundtruth*' | head -n 1)
    [[ -n "$gt" ]] || log "note: no ground-truth file found in $out; loop-closure scoring needs it"
    img_dir=$(find "$out" -type f \( -iname '*.jpg' -o -iname '*.png' -o -iname '*.ppm' \) -printf '%h\n' \
        | sort | uniq -c | sort -rn | head -n 1 | sed 's/^ *[0-9]* //')
    touch "$out/.complete"
    log "ready: images in $img_dir${gt:+, ground truth $gt}"
done
exit "$status"
