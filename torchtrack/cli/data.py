"""``torchtrack data fetch NAME``: get a data set the benchmarks need, checksums verified."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from torchtrack.cli._common import add_common_options
from torchtrack.io.datasets import CLIF2007, DATASETS, WPAFB
from torchtrack.io.outputs import write_json

NAME = "data"
HELP = "get the real data sets: WPAFB truth and frames, CLIF 2007 frames (data fetch wpafb|clif2007)"
DESCRIPTION = f"""Get the data sets that some commands need; they are not part of the repository.

  wpafb  {WPAFB.title}
         (WPAFB 2009, AFRL public release), as published in github.com/{WPAFB.repository}
         (licence: {WPAFB.licence}). Needed by torchtrack track --benchmark wpafb, torchtrack tune
         --config tune-gmphd-wpafb and the real-frame part of torchtrack eval-detector.

  clif2007  {CLIF2007.title},
         as published in github.com/{CLIF2007.repository} (AFRL public release; the repository states no
         licence). Real wide-area video without truth, for torchtrack track --frames data/clif2007/frames
         (docs/real-video.md).

Commands look for WPAFB in ./data/{WPAFB.folder} (also in the source checkout's data/), then in
${WPAFB.env}, then in ../shared/data/{WPAFB.folder}; data/README.md describes the files.

action:
  fetch NAME   download the files into data/<folder> (--out DIR), each checked against the SHA-256 that
               torchtrack ships, and record the source and licence beside them (SOURCE.md, SHA256SUMS).
               Nothing is left under a final name unless it is verified; running it again when all is
               there does nothing. --from DIR copies from a local copy instead (an offline machine).

examples:
  torchtrack data fetch wpafb
  torchtrack data fetch wpafb --from ../shared/data/{WPAFB.folder}
  torchtrack data fetch clif2007
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    fetch = actions.add_parser("fetch", help="download a data set, checksums verified",
                               description="Download a data set into data/<folder>, checksums verified.")
    fetch.set_defaults(_parser=fetch)
    fetch.add_argument("dataset", choices=sorted(DATASETS), help="the data set")
    fetch.add_argument("--out", type=Path, default=None, help="folder to fill (default data/<folder>, "
                       f"e.g. data/{WPAFB.folder})")
    origin = fetch.add_mutually_exclusive_group()
    origin.add_argument("--url", default=None, help="base URL that replaces the repository's raw-file root "
                        f"(a mirror; default ${WPAFB.env}_URL, else {WPAFB.base_url})")
    origin.add_argument("--from", dest="source", type=Path, default=None, metavar="DIR",
                        help="copy from a local folder in the data set's layout instead of downloading")
    fetch.add_argument("--timeout", type=float, default=60.0, help="network timeout in seconds (default 60)")
    fetch.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_common_options(fetch, random=False)


def run(args: argparse.Namespace) -> int:
    from torchtrack.io.fetch import fetch_dataset

    dataset = DATASETS[args.dataset]  # argparse choices: a known name
    out = args.out or Path("data") / dataset.folder
    url = args.url or os.environ.get(dataset.url_env) or None
    result = fetch_dataset(dataset, out, base_url=url, source=args.source, progress=not args.no_progress,
                           timeout=args.timeout)
    if result.changed:
        done = f"{len(result.fetched)} fetched, {len(result.replaced)} replaced, {len(result.kept)} already there"
        print(f"{dataset.name}: {done}; all {len(dataset.files)} files verified in {out} "
              f"(from {result.origin}; source and licence in {out / 'SOURCE.md'})")
    else:
        print(f"{dataset.name}: all {len(dataset.files)} files already present and verified in {out}; "
              "nothing to do")
    write_json(args.json, {"dataset": dataset.name, "folder": str(out), "origin": result.origin,
                           "fetched": list(result.fetched), "replaced": list(result.replaced),
                           "kept": list(result.kept)})
    return 0
