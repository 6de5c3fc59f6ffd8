#!/usr/bin/env bash
# Download EuRoC MAV sequences in ASL format (Burri et al., IJRR 2016) and check them.
#
# Usage: data_scripts/euroc.sh [-o DIR] [--archive FILE.zip] [--checksum HASH] [--dry-run] SEQ...
#   SEQ      MH_01_easy MH_02_easy MH_03_medium MH_04_difficult MH_05_difficult
#            V1_01_easy V1_02_medium V1_03_difficult V2_01_easy V2_02_medium V2_03_difficult
#            (default: V1_01_easy)
#   -o DIR   where to put the sequences (default: data/euroc); each lands in DIR/SEQ/mav0/
#   --archive FILE   use an already downloaded zip: either a room zip from the ETH Research
#                    Collection (machine_hall.zip, vicon_room1.zip, vicon_room2.zip) or a
#                    single sequence's ASL zip (SEQ.zip); for one room / one SEQ
#   --checksum HASH  md5 or sha256 the downloaded zip must have (the Research Collection
#                    page lists an MD5 per file)
#   --dry-run        print what would be fetched, fetch nothing
#
# Where the data lives: ASL's original server (robotics.ethz.ch/~asl-datasets) has been
# retired; the dataset is now in the ETH Research Collection,
#   https://www.research-collection.ethz.ch/entities/researchdata/bcaf173e-5dac-484b-bc37-faf97a594f1f
# which serves one zip per room (machine hall about 12 GB, each Vicon room about 6 GB)
# holding ROOM/SEQ/SEQ.zip (ASL format) and ROOM/SEQ/SEQ.bag. The file links below are the
# ones known when this script was written and MAY CHANGE: if a download fails, open the page
# above, download the room zip by hand and pass it with --archive, or set EUROC_URL_MH,
# EUROC_URL_V1 or EUROC_URL_V2 to the new link.
#
# Downloads are resumable. Each zip is tested with unzip -t (and its sha256 recorded in
# SHA256SUMS beside it); after extraction the number of images in mav0/cam0/data must
# equal the number of lines of mav0/cam0/data.csv. Only the requested sequences are
# extracted; the room zip is kept so that other sequences of the room need no download.
# Read with: open_sequence("euroc", "DIR/V1_01_easy") (ground truth from
# mav0/state_groundtruth_estimate0, moved into the cam0 frame with T_BS).
set -o errexit -o nounset -o pipefail
# shellcheck source=SCRIPTDIR/common.sh
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"

RC=https://www.research-collection.ethz.ch/bitstreams
URL_MH=${EUROC_URL_MH:-$RC/7b2419c1-62b5-4714-b7f8-485e5fe3e5fe/download}
URL_V1=${EUROC_URL_V1:-$RC/02ecda9a-298f-498b-970c-b7c44334d880/download}
URL_V2=${EUROC_URL_V2:-$RC/ea12bc01-3677-4b4c-853d-87c7870b8c44/download}
KNOWN="MH_01_easy MH_02_easy MH_03_medium MH_04_difficult MH_05_difficult V1_01_easy V1_02_medium V1_03_difficult V2_01_easy V2_02_medium V2_03_difficult"

DEST=data/euroc
ARCHIVE=""
CHECKSUM=""
SEQS=()
while [[ $# -gt 0 ]]; do
    case $1 in
        -o | --output) DEST=${2:?-o needs a folder}; shift 2 ;;
        --archive) ARCHIVE=${2:?--archive needs a file}; shift 2 ;;
        --checksum) CHECKSUM=${2:?--checksum needs a hash}; shift 2 ;;
        --dry-run) DRY_RUN=1; shift ;;
        -h | --help) usage 0 ;;
        -*) log "unknown option $1"; usage 2 ;;
        *) SEQS+=("$1"); shift ;;
    esac
done
[[ ${#SEQS[@]} -gt 0 ]] || SEQS=(V1_01_easy)
for seq in "${SEQS[@]}"; do
    [[ " $KNOWN " == *" $seq "* ]] || die "unknown EuRoC sequence '$seq'; one of: $KNOWN"
done
need unzip sha256sum find

# room SEQ: the room folder name and its zip URL.
room_of() {
    case $1 in
        MH_*) ROOM=machine_hall URL=$URL_MH ;;
        V1_*) ROOM=vicon_room1 URL=$URL_V1 ;;
        V2_*) ROOM=vicon_room2 URL=$URL_V2 ;;
    esac
}

# extract_sequence SEQ_ZIP SEQ: unzip one sequence's ASL zip into DEST/SEQ and check it.
extract_sequence() {
    local zip=$1 seq=$2 out=$DEST/$2 cam
    verify_archive "$zip"
    run mkdir -p "$out"
    log "extracting $seq"
    run unzip -q -o "$zip" -d "$out"
    [[ "$DRY_RUN" == 1 ]] && return 0
    cam=$out/mav0/cam0
    [[ -f "$cam/data.csv" ]] || die "$cam/data.csv missing after extraction: not an ASL-format EuRoC zip?"
    expect_count "$seq/mav0/cam0/data" "$(count_files "$cam/data" '*.png')" "$(data_lines "$cam/data.csv")"
    [[ -f "$out/mav0/state_groundtruth_estimate0/data.csv" ]] \
        || log "note: $seq has no mav0/state_groundtruth_estimate0/data.csv"
    touch "$out/.complete"
    log "ready: $out"
}

for seq in "${SEQS[@]}"; do
    if [[ -f "$DEST/$seq/.complete" ]]; then
        log "$seq already extracted in $DEST/$seq"
        continue
    fi
    room_of "$seq"
    if [[ -n "$ARCHIVE" && "$(basename "$ARCHIVE")" == "$seq.zip" ]]; then
        expect_hash "$ARCHIVE" "$CHECKSUM"
        extract_sequence "$ARCHIVE" "$seq"
        continue
    fi
    room_zip=${ARCHIVE:-$DEST/$ROOM.zip}
    [[ -n "$ARCHIVE" ]] || fetch "$URL" "$room_zip"
    verify_archive "$room_zip"
    expect_hash "$room_zip" "$CHECKSUM"
    inner=$ROOM/$seq/$seq.zip
    if [[ "$DRY_RUN" != 1 ]]; then
        # The room zip is expected to hold ROOM/SEQ/SEQ.zip; accept any folder prefix.
        inner=$(unzip -Z1 "$room_zip" | grep -m1 "\(^\|/\)$seq\.zip\$" || true)
        [[ -n "$inner" ]] || die "no $seq.zip inside $room_zip (list it with: unzip -l $room_zip); pass the sequence zip with --archive"
    fi
    tmp=$DEST/.unpack_$seq
    log "taking $inner out of $(basename "$room_zip")"
    run mkdir -p "$tmp"
    run unzip -q -o "$room_zip" "$inner" -d "$tmp" || die "cannot extract $inner from $room_zip"
    extract_sequence "$tmp/$inner" "$seq"
    run rm -rf "$tmp"
done
