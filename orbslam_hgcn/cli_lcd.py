"""The ``orbslam-hgcn lcd`` command: the paper's loop-closure detectors (BoW, HGCN-BoW,
FAB-MAP 2.0, HGCN-FABMAP) on place-recognition datasets. Its arguments are declared here and
registered by :mod:`orbslam_hgcn.cli`; the work is :mod:`orbslam_hgcn.placerec.lcd`."""

from __future__ import annotations

import argparse


def add_lcd(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "lcd",
        help="compare loop-closure detectors (BoW, HGCN-BoW, FAB-MAP 2.0, HGCN-FABMAP)",
        description="Train each detector on --train, run it over --test, score its confusion "
        "matrix against the ground-truth loop matrix (recall, accuracy = precision, recall at "
        "100% precision, AUC); write confusion matrices, PR curves and lcd_results.json. "
        "The memory each detector needs (its (n, n) matrices over the test images; FAB-MAP: its "
        "per-word tables and Chow-Liu tree, linear in the vocabulary) is checked against the memory "
        "available (or $ORBSLAM_HGCN_MEMORY_LIMIT_MB) before it runs; when it does not fit, the command stops "
        "with status 2: use a smaller vocabulary, --levels, or fewer images. By default a video-rate "
        "sequence is sampled to about one image per distinct view (0.25 m or 15 deg of ground-truth "
        "camera motion, else one image per 0.5 s). When its loop ground truth covers every frame and "
        "that leaves fewer than 20 images that revisit an earlier one outside the exclusion window, or "
        "fewer than 80 images, the spacing shrinks step by step (to 84% each, at last every frame) "
        "until both are met; when even the densest cannot give 20, a warning says so. images_test.txt "
        "and images_train.txt name the images used. A query is compared only with images outside an "
        "exclusion window, chosen on the images as used: the ground truth's smallest loop separation, "
        "else 10 s; the loops scored are the ground truth's revisits (true pairs joined to the "
        "diagonal are one continuous visit, not loops, whatever the spacing). The recall/accuracy "
        "thresholds are fitted on the training sequence (highest recall at 100% precision there; it "
        "needs TRAIN/loop_gt.npy or --train-gt). AUC and recall at 100% precision are printed and "
        "written with 95% confidence intervals: percentile bootstrap over the test queries (1000 "
        "resamples with replacement, fixed seed), so that a figure from a few true loops reads as "
        "uncertain as it is.",
    )
    p.add_argument("--method", default="all",
                   help="bow, hgcn-bow, fabmap2, hgcn-fabmap, a comma list, or all (default)")
    p.add_argument("--train", required=True, help="training sequence (image folder or dataset)")
    p.add_argument("--test", required=True, help="test sequence (image folder or dataset)")
    p.add_argument("--gt", default=None,
                   help="ground-truth loop matrix of the test images (.mat, .txt, .csv, .npy); "
                   "default TEST/loop_gt.npy")
    p.add_argument("--train-gt", default=None,
                   help="ground-truth loop matrix of the training images, for fitting the thresholds; "
                   "default TRAIN/loop_gt.npy when present")
    p.add_argument("--vocab", default=None,
                   help="one vocabulary for every method: orb, hgcn or a file (default: ORB tree "
                   "for bow/fabmap2, HGCN vocabulary for hgcn-*)")
    p.add_argument("--vocab-orb", default=None,
                   help="ORB-tree vocabulary for bow and fabmap2 (default orb10k: the ORB tree at about the HGCN's "
                   "size, trained on the same photographs; 'orb' for the ORB-SLAM-shaped tree)")
    p.add_argument("--vocab-hgcn", default=None, help="HGCN vocabulary file for hgcn-bow and hgcn-fabmap")
    p.add_argument("--levels", type=int, default=None, metavar="N",
                   help="ORB-tree vocabularies: take as words the tree's nodes N levels below the root "
                   "(at most k^N words; the shipped tree has k=10, 6 levels) instead of its leaves")
    p.add_argument("--features", choices=("orb", "sift"), default="orb",
                   help="local features (sift stands in for SURF; default orb)")
    p.add_argument("--n-features", type=int, default=1000, help="features per image (default 1000)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", default=None, help="YAML file with a 'fabmap:' section (FabmapConfig)")
    p.add_argument("--new-place", choices=("mean_field", "sampled"), default=None,
                   help="FAB-MAP new-place likelihood (default from config: mean_field)")
    window = p.add_mutually_exclusive_group()
    window.add_argument("--min-gap", type=int, default=None,
                        help="compare a query only with images at least this many images earlier, counted in "
                        "the sampled images (one per distinct view by default; when they are made denser for "
                        "too few revisits, the gap is scaled up by as much) (default: the ground truth's "
                        "smallest loop separation, else --window-s 10)")
    window.add_argument("--window-s", type=float, default=None,
                        help="compare a query only with images at least this many seconds earlier")
    p.add_argument("--threshold", type=float, default=None,
                   help="FAB-MAP acceptance probability for recall/accuracy (default: fitted on the "
                   "training sequence, else 0.99)")
    p.add_argument("--bow-threshold", type=float, default=None,
                   help="BoW acceptance cosine similarity for recall/accuracy (default: fitted on the "
                   "training sequence, else 0.3)")
    sampling = p.add_mutually_exclusive_group()
    sampling.add_argument("--stride", type=int, default=None,
                          help="use every stride-th image of both sequences, never made denser (default: "
                          "sampled by camera motion or time, denser for too few revisits, see above)")
    sampling.add_argument("--every-s", type=float, default=None,
                          help="use one image per this many seconds of both sequences")
    p.add_argument("--limit", type=int, default=None, help="use at most this many images of each")
    p.set_defaults(func=run_lcd)


def run_lcd(args: argparse.Namespace) -> int:
    import dataclasses

    from orbslam_hgcn.config import FabmapConfig, load_yaml, section_from_yaml
    from orbslam_hgcn.errors import ConfigError
    from orbslam_hgcn.outputs import check_output_folder
    from orbslam_hgcn.placerec import lcd

    check_output_folder(args.out)
    if args.n_features < 1:
        raise ConfigError(f"--n-features must be at least 1, found {args.n_features}")
    cfg = FabmapConfig()
    if args.config:
        cfg = section_from_yaml(FabmapConfig, load_yaml(args.config), args.config, "fabmap")
    if args.new_place is not None:
        cfg = dataclasses.replace(cfg, new_place=args.new_place)
    if args.min_gap is not None:
        cfg = dataclasses.replace(cfg, min_gap=args.min_gap)
    run = lcd.lcd_command(
        method=args.method, train=args.train, test=args.test, gt=args.gt, train_gt=args.train_gt, out=args.out,
        features=args.features, vocab=args.vocab, vocab_orb=args.vocab_orb, vocab_hgcn=args.vocab_hgcn,
        cfg=cfg, stride=args.stride, every_s=args.every_s, window_s=args.window_s, limit=args.limit,
        n_features=args.n_features, levels=args.levels,
        fabmap_threshold=args.threshold, bow_threshold=args.bow_threshold,
    )
    for line in run.lines:
        print(line)
    print(lcd.format_table(run.results))
    for path in run.paths:
        print(f"wrote {path}")
    return 0
