"""``torchtrack draw``: a MOTChallenge tracks file drawn over its frames or video (:mod:`torchtrack.pipeline.draw`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from torchtrack.cli._common import add_common_options, add_force_option, positive_float, positive_int
from torchtrack.errors import TorchtrackError
from torchtrack.io.outputs import OutputFolder, check_output_file, write_json
from torchtrack.io.video_writer import CODECS

NAME = "draw"
HELP = "draw a tracks file (and its truth and detections) over its frames or video into an annotated video or PNGs"
DESCRIPTION = """Draw a MOTChallenge tracks file over the frames it was made from (--frames DIR or --video FILE;
frame k of the file is the k-th image of the folder or the video, from 1), optionally with the truth (--gt) and the
detections (--detections), into an annotated MP4 (--out FILE.mp4) or a folder of PNGs (--out DIR).

Each track is a dot (or a box, --box) in its identity's colour with its number and a line through its last
--trail positions; truth is drawn as white crosses, detections as yellow rings, the frame number top-left,
and a legend band under every frame says what the colours and marks mean. torchtrack track writes its
annotated.mp4 with the same drawing.

The video is H.264, which browsers play, where PyAV is installed (pip install 'torchtrack-mtt[video]');
otherwise MPEG-4 part 2 (mp4v), which desktop players play but browsers do not (--codec chooses). A frame of
odd width or height is padded by a black column or row, never cropped. The video appears under its name when
it is complete (written as NAME.partial.mp4 until then); PNGs appear in --out together.

Examples:
  torchtrack draw --tracks out/seq/tracks.txt --frames seq/frames --gt seq/gt.txt --out out/seq/drawn.mp4
  torchtrack draw --tracks out/clip/tracks.txt --video clip.mp4 --detections out/clip/detections.txt \\
      --out out/clip/frames --scale 2
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--tracks", type=Path, required=True, metavar="TXT",
                        help="the tracks to draw (MOTChallenge text, e.g. tracks.txt of torchtrack track)")
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--frames", type=Path, metavar="DIR", help="the frames: a folder of images (natural order)")
    src.add_argument("--video", type=Path, metavar="FILE", help="the frames: a video file")
    parser.add_argument("--gt", type=Path, default=None, metavar="TXT", help="truth to draw as white crosses")
    parser.add_argument("--detections", type=Path, default=None, metavar="TXT",
                        help="detections to draw as yellow rings (e.g. detections.txt of torchtrack track)")
    parser.add_argument("--out", type=Path, required=True,
                        help="an .mp4 file for a video, otherwise a folder for one PNG per frame")
    parser.add_argument("--trail", type=int, default=12, metavar="N",
                        help="past positions drawn per identity (0: no trails)")
    parser.add_argument("--box", type=positive_int, default=None, metavar="PX",
                        help="draw each track as a box of this side (default: a dot)")
    parser.add_argument("--scale", type=positive_int, default=1, help="enlarge the frames this many times")
    parser.add_argument("--fps", type=positive_float, default=10.0, help="frame rate of the video")
    parser.add_argument("--codec", choices=CODECS, default="auto",
                        help="auto: H.264 where PyAV is installed, else mp4v")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_force_option(parser, "a PNG folder --out")
    add_common_options(parser, random=False)


def run(args: argparse.Namespace) -> int:
    from torchtrack.io.frames import open_frames
    from torchtrack.io.mot import read_mot
    from torchtrack.pipeline.draw import draw

    if args.trail < 0:
        raise TorchtrackError(f"--trail must be >= 0; got {args.trail}")
    png = args.out.suffix.lower() != ".mp4"
    inputs = [args.tracks, args.gt, args.detections, args.frames or args.video]
    if not png:
        check_output_file(args.out)
        if any(p is not None and Path(p).resolve() == args.out.resolve() for p in inputs):
            raise TorchtrackError(f"--out {args.out}: is one of the inputs")
    source = open_frames(args.frames or args.video, color=True)
    tracks = read_mot(args.tracks)
    truth = read_mot(args.gt) if args.gt else None
    detections = read_mot(args.detections) if args.detections else None
    options = {"png": png, "fps": args.fps, "trail": args.trail, "box": args.box, "scale": args.scale,
               "codec": args.codec, "progress": not args.no_progress,
               "names": {"tracks": str(args.tracks), "truth": str(args.gt), "detections": str(args.detections)}}
    if png:
        with OutputFolder(args.out, f"torchtrack {NAME}", args.force, inputs=inputs) as staging:
            drawn = draw(source, tracks, staging, truth, detections, **options)
        drawn.path = args.out
    else:
        drawn = draw(source, tracks, args.out, truth, detections, **options)
    kind = "PNGs" if png else f"{drawn.codec} video"
    print(f"drew {drawn.frames} frames ({drawn.size[0]}x{drawn.size[1]} px, legend included) into {kind} {drawn.path}")
    write_json(args.json, {"frames": drawn.frames, "out": str(drawn.path), "codec": drawn.codec,
                           "width": drawn.size[0], "height": drawn.size[1]})
    return 0
