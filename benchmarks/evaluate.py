"""Score a result folder against the ground truth of a scene (``mvintrinsic.evaluation.evaluate``).

::

    python benchmarks/evaluate.py SCENE RESULT [--views V ...] [--out scores.json] [--window 20] [--step 10]
    python benchmarks/evaluate.py SCENE --gt-as-result OUT [--views V ...] [--out scores.json]

Prints a table (one row per view and the mean) on stdout. The scores are written as JSON only
when ``--out`` is given (``--out -`` prints the JSON instead of the table): nothing is ever
written into the result folder unasked.

``--gt-as-result OUT`` is the self-check of the evaluation: it writes the scene's own ground truth
as a result folder to OUT (``ground_truth_decomposition`` + ``save_decomposition``; OUT must not
lie inside the scene) and scores it, which must give LMSE 0, si-MSE 0 and BER 0.

Errors in the input are reported on one line naming the file, with exit status 2. Run with the
package importable (installed, or ``PYTHONPATH`` pointing at the checkout).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mvintrinsic.evaluation import evaluate, ground_truth_decomposition
from mvintrinsic.io import ResultFolderError, SceneError, save_decomposition, write_json

#: (JSON key, column title, format) of the table.
COLUMNS = (
    ("lmse_reflectance", "LMSE_R", ".4g"),
    ("lmse_shading", "LMSE_S", ".4g"),
    ("lmse_score", "score", ".4g"),
    ("si_mse_reflectance", "siMSE_R", ".4g"),
    ("si_mse_shading", "siMSE_S", ".4g"),
    ("ber", "BER", ".4f"),
    ("ber_excluded_fraction", "BER_excl", ".3f"),
    ("reconstruction_psnr", "PSNR_RS", ".2f"),
    ("reconstruction_ssim", "SSIM_RS", ".5f"),
    ("shading_psnr", "PSNR_S", ".2f"),
    ("shading_ssim", "SSIM_S", ".5f"),
)


def format_table(scores: dict[str, Any]) -> str:
    """The per-view scores and their mean as a fixed-width text table."""
    rows = [("view", *(title for _, title, _ in COLUMNS))]
    for name, values in [*scores["views"].items(), ("mean", scores["mean"])]:
        rows.append((name, *("-" if values[k] is None else format(values[k], f) for k, _, f in COLUMNS)))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = [
        "  ".join(cell.rjust(w) if i else cell.ljust(w) for i, (cell, w) in enumerate(zip(row, widths, strict=True)))
        for row in rows
    ]
    lines.insert(1, "-" * len(lines[0]))
    lines.insert(len(lines) - 1, "-" * len(lines[0]))
    sun = scores["lighting"]["sun_direction_error_deg"]
    lines.append(f"sun direction error: {'-' if sun is None else f'{sun:.3f} deg'}")
    if scores["views_without_result"]:
        lines.append(f"not in the result (not scored): {', '.join(scores['views_without_result'])}")
    if scores["views_without_gt"]:
        lines.append(f"without ground truth (not scored): {', '.join(scores['views_without_gt'])}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scene", type=Path, help="scene folder with gt/")
    parser.add_argument("result", type=Path, nargs="?", help="result folder to score (omit with --gt-as-result)")
    parser.add_argument(
        "--gt-as-result", type=Path, metavar="OUT", help="write the ground truth as a result to OUT and score it"
    )
    parser.add_argument("--views", nargs="+", metavar="STEM", help="score only these views")
    parser.add_argument("--out", metavar="FILE", help="write the scores as JSON to FILE ('-': print JSON, no table)")
    parser.add_argument("--window", type=int, default=20, help="LMSE window side in pixels (default 20)")
    parser.add_argument("--step", type=int, default=10, help="LMSE window stride in pixels (default 10)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if (args.result is None) == (args.gt_as_result is None):
        parser.error("give exactly one of RESULT or --gt-as-result OUT")
    try:
        result = args.result
        if args.gt_as_result is not None:
            result = save_decomposition(
                ground_truth_decomposition(args.scene, views=args.views), args.gt_as_result, scene=args.scene
            )
        scores = evaluate(args.scene, result, views=args.views, window=args.window, step=args.step)
    except (SceneError, ResultFolderError, ValueError) as exc:
        print(f"evaluate: error: {exc}", file=sys.stderr)
        return 2
    if args.out == "-":
        print(json.dumps(scores, indent=1, allow_nan=False))
        return 0
    print(format_table(scores))
    if args.out is not None:
        print(f"scores written to {write_json(args.out, scores)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
