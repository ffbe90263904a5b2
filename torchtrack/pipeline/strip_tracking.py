"""Tracking over horizontal strips, one strip per rank of a process group, with identities agreed across the
strips' seams (under ``torchrun``, ``torch.distributed``).

**Strips.** The seams are the inner boundaries of ``strip_rows(height, W)`` (:mod:`torchtrack.pipeline.strips`).
Rank ``r`` *owns* the rows ``[s_r, s_{r+1})`` between its seams (the first strip reaches up to −∞, the last
down to +∞, so every position has one owner). Every rank is given the whole frame's detections; rank ``r``
runs its own tracker on those whose ``y`` lies in its *window*: its rows widened by ``band`` px on each side
(the handover band).

**Identities** (:class:`Identities`, run identically on every rank on the all-gathered reports, so every rank
holds the same result). Each frame every rank sends all the tracks its tracker reports, ``(local id,
position)``. A global identity ``g`` has one *owner*, a rank and its local id, whose estimate is ``g``'s
position:

1. ``g`` continues while its owner's local id is reported;
2. **handover**: when the owner's estimate of ``g`` lies outside its rows, the rank owning that position
   takes ``g`` over with its local track nearest that estimate within ``match_distance`` px (pairs nearest
   first; a track that received an identity this frame is not taken again). If that track already reports an
   identity of its own (the receiver had taken the vehicle for a new one), that identity ends and ``g``
   continues. With no track in reach, the owner keeps ``g`` (its estimate, in its band) and tries again
   next frame;
3. **new**: a local track in its rank's own rows that reports no identity is the *shadow* of another rank's
   track (the same vehicle seen in the band) when a track reported by another rank lies within
   ``match_distance`` px, and is left out; otherwise it takes the identity it held last (a local label the
   tracker resumed) if that identity is not reported, else a new identity (candidates in rank order).

The merged tracks of the whole frame, global ids in increasing order, are returned on every rank. The
owners and last identities are kept for every identity issued (a few dictionary entries each). The detections'
grey levels (``tones``) follow the detections into the window; the tracker's pending new tracks
(``pending_positions``, which the video pipeline's weak detections may continue) are all-gathered with the
reports, each kept by the rank owning its position, so that every rank's stream sees the whole frame's.

**What equals one process.** The enhanced GM-PHD (the tracker this was built and tested for; the others
run too but are not examined here) is local: its update, birth, merge and label fix couple a track only to
detections and components within the gate (≈ 4.3 σ of the innovation, 10–15 px here) or the birth distance
``T_B``, its clutter intensity is a constant per px², and its label hand-over resumes a lost
label within ``handover_distance`` (20 px) of its position extrapolated over up to ``handover_frames`` (8)
frames. A track whose vehicle stays farther than ``band`` from every seam in one process is 2 ``band``
inside its strip's window at every frame and sees the same detections and neighbours; with ``band`` above
those reaches it gets the *same* positions (to float rounding) and one global id (one process's ids up to a
one-to-one relabelling). Three shared things are not strictly local, and the equality holds where they do
not act:

- the enhanced GM-PHD's component cap sizes itself from the detections and labels given (here a strip's):
  a strip whose cap is hit drops different components (:attr:`StripTracker.cap_hits` counts this rank's);
- its velocity map is a grid over the image fed by the rank's own estimates, including those in the band;
  a birth in a cell last crossed by a vehicle that came over a seam takes that vehicle's strip estimate of
  the velocity, which differs slightly from one process's;
- a neighbour that crossed a seam carries its (slightly different) strip estimate into a shared gate, and a
  fast vehicle's lost label reaches ``handover_distance`` plus 8 frames of its motion.

In float32 the strips' different component counts and orders round differently (1e-4 px at 2000 px), which
now and then flips a near-tie far from any seam; the equality is a float64 statement.

**What does not.** A track that comes within ``band`` of a seam is tracked twice. The receiving rank's track
starts when its vehicle enters the receiving window (a birth, confirmed two frames later, whose Kalman
estimate has not quite forgotten its start), so after a handover the position is the receiver's estimate,
typically within 1e-3 px of one process's; a handover that finds no match within ``match_distance`` leaves
the track with its sender until lost, and a vehicle that reaches the seam before the receiver confirms it
(faster than about ``band / 3`` px per frame across the seam) may briefly be missing or switch identity. A
shadow test against a different vehicle within ``match_distance`` px across a seam leaves that vehicle out
for the frame. ``tests/test_strip_tracking.py`` measures these differences as CLEAR-MOT against one process.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor

from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import Tracker
from torchtrack.pipeline.strips import rank_and_size, strip_rows

BAND = 48.0
"""Default handover band (px): the GM-PHD label hand-over's reach at 3.5 px/frame (``handover_distance`` 20 px
plus 8 frames of motion), which also covers the gate (≈ 15 px) and a new track's birth and confirmation
(3 frames) before its vehicle reaches the seam. Chosen on simulated scenes (``bench.scale.simulate``, seeds
1–3, 600 vehicles, 30 frames: bands 16–64 all gave one process's tracks within 1 px; 16 did not at 400
vehicles, seed 1)."""

MATCH_DISTANCE = 5.0
"""Default distance (px) within which two ranks' tracks are taken for the same vehicle: well above how far two
ranks' estimates of one vehicle lie apart at a handover (typically under 1e-3 px in the measured runs, once the receiver
has filtered the band), below the spacing of most vehicles (one per 60 × 60 px in ``bench.scale``)."""


@dataclass(frozen=True)
class StripConfig:
    """``height``: rows ``0`` to ``height`` split by :func:`~torchtrack.pipeline.strips.strip_rows` (the seams; the
    outer strips reach past them); ``band``: px each side of a strip its tracker also sees; ``match_distance``:
    px within which two ranks' tracks are one vehicle (module docstring)."""

    height: int
    band: float = BAND
    match_distance: float = MATCH_DISTANCE

    def __post_init__(self) -> None:
        if not (self.band >= 0 and np.isfinite(self.band)):
            raise TorchtrackError(f"strips: band must be a distance >= 0 px, got {self.band}")
        if not (self.match_distance > 0 and np.isfinite(self.match_distance)):
            raise TorchtrackError(f"strips: match_distance must be a positive distance in px, got "
                                  f"{self.match_distance}")

    def seams(self, parts: int) -> list[float]:
        """The ``parts − 1`` seam rows between ``parts`` strips."""
        return [float(y1) for _, y1 in strip_rows(self.height, parts)[:-1]]


Report = tuple[np.ndarray, np.ndarray]
"""One rank's tracks of a frame: local ``ids (n,)`` int64 and ``positions (n, 2)`` float64."""


class Identities:
    """The global identities of the strips' tracks (module docstring, rules 1–3); every rank keeps one and
    feeds it the same reports, so all agree."""

    def __init__(self, seams: Sequence[float], match_distance: float):
        self.seams = list(seams)
        self.match_distance = match_distance
        self.owner: dict[int, tuple[int, int]] = {}     # global id -> (rank, local id)
        self.held: dict[tuple[int, int], int] = {}      # (rank, local id) -> the global id it held last
        self.next_id = 1

    def rank_of(self, y: np.ndarray) -> np.ndarray:
        """The ranks owning rows ``y``."""
        return np.searchsorted(self.seams, y, side="right")

    def assign(self, reports: Sequence[Report]) -> tuple[np.ndarray, np.ndarray]:
        """Global ``ids (E,)`` (increasing) and ``positions (E, 2)`` of a frame from every rank's report."""
        row = [{lid: i for i, lid in enumerate(ids.tolist())} for ids, _ in reports]

        def position(key: tuple[int, int]) -> np.ndarray:
            return reports[key[0]][1][row[key[0]][key[1]]]

        owner_rank = [self.rank_of(pos[:, 1]) for _, pos in reports]                      # of each position
        out = {g: key for g, key in self.owner.items() if key[1] in row[key[0]]}       # 1. continuing
        pairs = []                                                                        # 2. handover
        for rank, (ids, pos) in enumerate(reports):
            leave = np.flatnonzero(owner_rank[rank] != rank)
            for lid, p, target in zip(ids[leave].tolist(), pos[leave], owner_rank[rank][leave].tolist()):
                g = self.held.get((rank, lid))
                if g is None or out.get(g) != (rank, lid):
                    continue
                near = np.hypot(*(reports[target][1] - p).T)
                pairs += [(float(near[i]), g, target, int(reports[target][0][i]))
                          for i in np.flatnonzero(near <= self.match_distance)]
        leaving = {g for _, g, _, _ in pairs}
        reporter = {key: g for g, key in out.items()}
        for _, g, target, lid in sorted(pairs):
            key = (target, lid)
            duplicate = reporter.get(key)
            if g not in out or out[g][0] == target or duplicate in leaving:
                continue
            if duplicate is not None:      # the receiver reports this vehicle already: one identity, g's
                del out[duplicate], self.owner[duplicate]
            del reporter[out[g]]
            out[g] = self.owner[g] = key
            reporter[key] = self.held[key] = g
            leaving.add(g)                 # a receiving track is not taken again
        reported = [(position(key), key[0]) for key in out.values()]                     # 3. new
        where = np.array([p for p, _ in reported]).reshape(-1, 2)
        by = np.array([r for _, r in reported], dtype=np.int64)
        added: list[tuple[np.ndarray, int]] = []
        for rank, (ids, pos) in enumerate(reports):
            free = ~np.isin(ids, [lid for r, lid in reporter if r == rank]) & (owner_rank[rank] == rank)
            for lid, p in zip(ids[free].tolist(), pos[free]):
                other = by != rank
                if (np.hypot(*(where[other] - p).T) <= self.match_distance).any() or any(
                        r != rank and np.hypot(*(q - p)) <= self.match_distance for q, r in added):
                    continue               # the shadow of another rank's track
                key = (rank, lid)
                g = self.held.get(key)
                if g is None or g in out:
                    g, self.next_id = self.next_id, self.next_id + 1
                out[g] = self.owner[g] = key
                self.held[key] = g
                added.append((p, rank))
        ids = np.array(sorted(out), dtype=np.int64)
        return ids, np.array([position(out[g]) for g in ids], dtype=np.float64).reshape(-1, 2)


class StripTracker:
    """A tracker over strips (module docstring) with the common tracker interface
    (:mod:`torchtrack.filters.trackers.protocol`): every rank of ``group`` (default: the default process group; none
    initialised: this process alone, one strip) calls ``step`` with the whole frame's detections and gets the
    whole frame's merged tracks. ``tracker`` is this rank's own tracker (any registered one)."""

    def __init__(self, tracker: Tracker, config: StripConfig, group: dist.ProcessGroup | None = None):
        self.tracker, self.config, self.group = tracker, config, group
        self.rank, self.world = rank_and_size(group)
        seams = config.seams(self.world)
        edges = [-np.inf, *seams, np.inf]
        self.window = (edges[self.rank] - config.band, edges[self.rank + 1] + config.band)
        self.reset()

    def reset(self) -> None:
        """Forget all tracks (global ids restart at 1)."""
        self.tracker.reset()
        self.identities = Identities(self.config.seams(self.world), self.config.match_distance)
        self.pending_positions = np.zeros((0, 2))

    @property
    def cap_hits(self) -> int:
        """This rank's tracker's component-cap hits (0 where it does not count them)."""
        return int(getattr(self.tracker, "cap_hits", 0))

    @property
    def tone_sigma(self) -> float | None:
        """This rank's tracker's ``tone_sigma`` (None where it takes no grey levels): ``step`` passes ``tones``
        on only where it is set."""
        return getattr(self.tracker, "tone_sigma", None)

    def step(self, frame: int, positions: Tensor, velocities: Tensor | None = None,
             tones: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Frame ``frame`` with the whole frame's detections ``positions (K, 2)`` (and ``velocities (K, 2)`` or
        None; their grey levels ``tones (K,)`` or None): the merged global ``ids (E,)`` and ``positions (E, 2)``
        (on the device and in the dtype of this rank's tracker's output).

        Where this rank's tracker has ``pending_positions`` (new tracks not yet reported), they are
        all-gathered with the tracks and :attr:`pending_positions` holds, after the step, those of every rank
        that lie in that rank's own rows."""
        positions = torch.as_tensor(positions)
        y = positions.reshape(-1, 2)[:, 1]
        mine = (y >= self.window[0]) & (y < self.window[1])
        extra = {} if tones is None else {"tones": torch.as_tensor(tones).reshape(-1)[mine]}
        ids, pos = self.tracker.step(frame, positions.reshape(-1, 2)[mine],
                                     None if velocities is None else torch.as_tensor(velocities).reshape(-1, 2)[mine],
                                     **extra)
        pending = getattr(self.tracker, "pending_positions", None)
        report = (ids.detach().cpu().numpy().astype(np.int64), pos.detach().cpu().double().numpy().reshape(-1, 2),
                  np.zeros((0, 2)) if pending is None else pending.detach().cpu().double().numpy().reshape(-1, 2))
        reports: list = [report]
        if self.world > 1:
            reports = [None] * self.world
            dist.all_gather_object(reports, report, group=self.group)
        self.pending_positions = np.concatenate(
            [p[self.identities.rank_of(p[:, 1]) == r] for r, (_, _, p) in enumerate(reports)])
        gids, merged = self.identities.assign([r[:2] for r in reports])
        return torch.as_tensor(gids, device=pos.device), torch.as_tensor(merged, dtype=pos.dtype, device=pos.device)
