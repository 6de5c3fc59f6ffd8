#!/usr/bin/env bash
# Fetch and unpack the KITTI odometry benchmark (Geiger et al., CVPR 2012): grayscale
# images, calibration and ground-truth poses, and check them.
#
# Usage: data_scripts/kitti.sh --gray URL|ZIP [--calib URL|ZIP] [--poses URL|ZIP]
#                              [-o DIR] [--dry-run] [SEQ...]
#   --gray   data_odometry_gray.zip (about 22 GB), as a download link or a local file
#   --calib  data_odometry_calib.zip (about 1 MB): calib.txt of every sequence
#   --poses  data_odometry_poses.zip (about 4 MB): ground truth of sequences 00-10
#   SEQ      sequences to unpack, e.g. 00 05 07 (default: all in the zip)
#   -o DIR   destination (default: data/kitti); gives DIR/dataset/sequences/NN/image_0,
#            times.txt, calib.txt and DIR/dataset/poses/NN.txt (the layout the reader expects)
#   --dry-run  print what would be done
#
# KITTI needs registration, so this script has no built-in links. To get them:
#   1. register (free, accepting the CC BY-NC-SA 3.0 licence) at
#      https://www.cvlibs.net/datasets/kitti/user_register.php
#   2. on https://www.cvlibs.net/datasets/kitti/eval_odometry.php follow
#      "Download odometry data set (grayscale, 22 GB)", "... (calibration files, 1 MB)"
#      and "Download odometry ground truth poses (4 MB)"; the site then gives a link for each
#   3. pass the links (or the zips you downloaded) to this script.
#
# Downloads are resumable. Each zip is tested with unzip -t (sha256 recorded in SHA256SUMS
# beside it). After unpacking, every sequence must have as many images in image_0/ as lines
# in times.txt, as many poses as images, and sequences 00-10 their published frame counts.
# Only image_0 (left grayscale camera) is unpacked; image_1 is skipped.
# Read with: open_sequence("kitti", "DIR/dataset/sequences/05").
set -o errexit -o nounset -o pipefail
# shellcheck source=SCRIPTDIR/common.sh
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"

# Frames per sequence of the odometry benchmark's training part (lines of times.txt).
declare -A FRAMES=([00]=4541 [01]=1101 [02]=4661 [03]=801 [04]=271 [05]=2761
    [06]=1101 [07]=1101 [08]=4071 [09]=1591 [10]=1201)

DEST=data/kitti
GRAY="" CALIB="" POSES=""
SEQS=()
while [[ $# -gt 0 ]]; do
    case $1 in
        -o | --output) DEST=${2:?-o needs a folder}; shift 2 ;;
        --gray) GRAY=${2:?--gray needs a link or zip}; shift 2 ;;
        --calib) CALIB=${2:?--calib needs a link or zip}; shift 2 ;;
        --poses) POSES=${2:?--poses needs a link or zip}; shift 2 ;;
        --dry-run) DRY_RUN=1; shift ;;
        -h | --help) usage 0 ;;
        -*) log "unknown option $1"; usage 2 ;;
        *) [[ $1 =~ ^[0-9]{1,2}$ ]] || die "'$1' is not a sequence number (00-21)"
           SEQS+=("$(printf '%02d' "$((10#$1))")"); shift ;;
    esac
done
if [[ -z "$GRAY" ]]; then
    log "no --gray link or zip given: KITTI downloads need registration."
    usage 2
fi
need unzip sha256sum find

# local_zip URL|ZIP DEFAULT_NAME: path of the zip, downloading it first when given a link.
local_zip() {
    local src=$1 name=$2
    if [[ -f "$src" ]]; then
        printf '%s\n' "$src"
    elif [[ $src =~ ^https?:// ]]; then
        fetch "$src" "$DEST/$name"
        printf '%s\n' "$DEST/$name"
    else
        die "'$src' is neither an existing file nor an http(s) link"
    fi
}

# unpack ZIP ARG...: extract the members matching the unzip patterns / options ARG.
unpack() {
    local zip=$1
    shift
    verify_archive "$zip"
    run mkdir -p "$DEST"
    log "unpacking $(basename "$zip")"
    # unzip exits 11 when a pattern matches nothing; that is checked per sequence below.
    run unzip -q -o "$zip" "$@" -d "$DEST" || [[ $? -eq 11 ]]
}

patterns=()
if [[ ${#SEQS[@]} -gt 0 ]]; then
    for s in "${SEQS[@]}"; do patterns+=("*sequences/$s/*"); done
else
    patterns=('*')
fi

gray_zip=$(local_zip "$GRAY" data_odometry_gray.zip)
unpack "$gray_zip" "${patterns[@]}" -x '*/image_1/*' 
if [[ -n "$CALIB" ]]; then
    calib_zip=$(local_zip "$CALIB" data_odometry_calib.zip)
    unpack "$calib_zip" "${patterns[@]}"
fi
if [[ -n "$POSES" ]]; then
    poses_zip=$(local_zip "$POSES" data_odometry_poses.zip)
    unpack "$poses_zip" '*'
fi
[[ "$DRY_RUN" == 1 ]] && exit 0

root=$DEST/dataset/sequences
[[ -d "$root" ]] || die "$root missing after unpacking: not KITTI odometry zips?"
if [[ ${#SEQS[@]} -eq 0 ]]; then
    mapfile -t SEQS < <(find "$root" -mindepth 1 -maxdepth 1 -type d -printf '%f\n' | sort)
fi
for s in "${SEQS[@]}"; do
    d=$root/$s
    [[ -f "$d/times.txt" ]] || die "$d/times.txt missing: sequence $s is not in the zips"
    n=$(data_lines "$d/times.txt")
    expect_count "sequences/$s/image_0" "$(count_files "$d/image_0" '*.png')" "$n"
    if [[ -n "${FRAMES[$s]:-}" ]]; then
        expect_count "sequences/$s (published frame count)" "$n" "${FRAMES[$s]}"
    fi
    if [[ -f "$d/calib.txt" ]] && grep -q '^P0:' "$d/calib.txt"; then :; else
        log "warning: $d/calib.txt has no P0; pass data_odometry_calib.zip with --calib"
    fi
    p=$DEST/dataset/poses/$s.txt
    if [[ -f "$p" ]]; then
        [[ "$(data_lines "$p")" -eq "$n" ]] || die "$p: $(data_lines "$p") poses for $n images"
        log "poses/$s.txt: $n poses, as expected"
    elif [[ -n "${FRAMES[$s]:-}" && -n "$POSES" ]]; then
        die "$p missing although the poses zip was given"
    fi
done
log "ready: $root (${SEQS[*]})"
