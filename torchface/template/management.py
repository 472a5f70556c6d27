"""Template management (paper Section 4): dissimilarity confidence, the pose-keyed mosaic and its search.

The tracker aligns every frame against stored templates, not against the previous frame
(:func:`torchface.tracker.track_step`). This module keeps those templates and judges the result; the per-frame
policy that uses it is :func:`torchface.tracker.managed.managed_step`.

Dissimilarity confidence (Section 4.1)
--------------------------------------
With a frame's estimated shape, pose, expression and light, the frame is resampled into the normalised face
(frontal, neutral, reference light; :func:`torchface.normalise.normalised_face`) and its fiducial patches are
tracked against the reference frame's with the inverse-compositional Lucas-Kanade of
:mod:`torchface.template.dissimilarity`: :func:`frame_dissimilarity`. A right estimate leaves the patches in
place (dissimilarity near 0, confidence near 1); a wrong pose, an occluder or another face displaces or
hides them. Per frame this runs at a small size (:attr:`TemplateConfig.normalised_size`, 64 px) with the
facing tests only (no z-buffer) so that it stays a fraction of the solve's time. The reference is that of the
mosaic entry nearest the estimated pose (each entry stores the normalised face of the frame it was built
from): far from the first pose the normalised face is resampled from oblique, foreshortened surface, and
against the first frame's a right estimate would score low.

Mosaic (Section 4.2)
--------------------
A :class:`Mosaic` holds, per stream, up to ``E`` entries, each the per-level templates built at one head
pose, keyed by the pose's bin ``(round(dyaw / yaw_bin), round(dpitch / pitch_bin))`` where ``dyaw, dpitch`` are
the angles less the reference's (:func:`pose_bins`). Entry 0 is the reference (the first frame's templates), in
bin ``(0, 0)``. The bins are keyed to the first pose, not to the camera's axis: a head that rests a few degrees
off that axis (the James scan's fit starts at 5 degrees of pitch) would otherwise never come within
``bin_centre_fraction`` of a bin centre on that axis, and its mosaic would never grow. An entry's
intensities are stored under the reference light: a template point seen with illumination ``lambda`` is
brought back with the inverse of Eq. 19,
``T = (I - lambda_2) / (1 + lambda_1 + (lambda_3, lambda_4, lambda_5) . n_cam)``
(:func:`torchface.appearance.illumination.remove_illumination`), so the illumination parameters mean the
same thing against every entry. Entries are stored compactly (triangle, barycentric coordinates,
intensity, validity per point); :func:`entry_templates` rebuilds the full :class:`Template` (positions,
expression basis and normals follow from the person's shape, :func:`~torchface.template.points.template_at`).
The expression basis of a point does not depend on the pose it was seen at, so aligning against an entry
re-estimates pose and expression together (the paper's "expression re-corrected too").

Search (recovery without a detector)
------------------------------------
:func:`search_mosaic` looks for the face anywhere in a (coarse) gray image: every stored entry's template
(or a subset of its points) is placed at the entry's rotation, at a grid of image positions and a few depths,
and scored by the zero-mean normalised cross-correlation of its intensities with the image (invariant to
the gain and bias of the light). The best placement starts a normal solve.

Shapes: ``B`` streams, ``E`` mosaic entries, ``N`` template points, ``S`` shape units, ``A`` animation units,
``L`` illumination terms, ``G x G`` the normalised face. Frames and units: :mod:`torchface.conventions`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, fields

import torch
from torch import Tensor

from torchface.appearance.illumination import remove_illumination
from torchface.backend import Backend, use_native
from torchface.geometry._checks import (
    check_bool, check_int, check_intrinsics, check_number, check_optional_int, check_reals,
)
from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import project_points
from torchface.geometry.so3 import matrix_to_axis_angle, matrix_to_euler
from torchface.model.face_model import FaceModel
from torchface.normalise.face import NormalisedFaceLayout, normalised_face, normalised_face_posed
from torchface.rendering.visibility import vertex_normals
from torchface.template.dissimilarity import (
    DissimilarityConfig,
    DissimilarityReference,
    DissimilarityResult,
    _gaussian_kernels,
    dissimilarity,
)
from torchface.template.points import Template, TemplatePixels, _of_dtype, template_at

__all__ = [
    "TemplateConfig",
    "MosaicLevel",
    "Mosaic",
    "SearchResult",
    "pose_bins",
    "frame_dissimilarity",
    "new_mosaic",
    "add_entries",
    "nearest_entries",
    "select_entries",
    "entry_templates",
    "light_normalised_intensity",
    "search_mosaic",
    "face_inside_fraction",
    "has_bin",
    "within_reach",
    "params_from_pose",
    "reference_face",
]


def _default_dissimilarity() -> DissimilarityConfig:
    # Scaled from the 128 px defaults to the 64 px normalised face: patches of 7 px, displacement scale
    # d0 = 0.75 px and search range 3 px. At most 5 Lucas-Kanade iterations: most patches converge in 2-3
    # (to 0.02 px); the loop runs while any patch is active, and the few that do not settle (a patch whose
    # mask support changes as it moves wanders by 0.1-1 px per iteration) would hold all the others to the
    # limit (5.0 iterations per frame on average with a limit of 8).
    # min_present_fraction stays 0. At 0.5 (at least half of the reference's patches present) the pooled
    # confidence AUROC rose from 0.975 to 0.983: on the James long run wrong estimates scored 0.3-0.94 on 3 of 9
    # patches, and a lost track at 83 degrees of yaw scored 0.58 on 1 and was taken as recovered. But it doubled
    # the false losses at turned poses in benchmark.py's 32 streams (185 against 95 stream-frames) and took
    # template management's overhead there from about 20% to 37%; and the recovery rules of
    # tracker.managed (a lost stream adopts a candidate that beats its track) recover that James run without it.
    return DissimilarityConfig(patch_size=7, num_patches=16, max_displacement=3.0, d0=0.75, iterations=5,
                               tolerance=0.02)  # fmt: skip


#: How much better a placement at a widened depth (:attr:`TemplateConfig.search_depth_widening`) must correlate
#: than the best at the base depths to be chosen by :func:`search_mosaic`.
_WIDENED_DEPTH_MARGIN = 0.1


@dataclass(frozen=True)
class TemplateConfig:
    """Settings of template management (module docstring; the per-frame policy is
    :func:`torchface.tracker.managed.managed_step`).

    Attributes:
        enabled: dissimilarity confidence, confidence gating and loss detection/recovery. False gives the
            bare tracker (``TrackResult.confidence`` is then the residual confidence).
        mosaic: keep a pose-keyed mosaic of templates and align against the entry nearest the pose.
        texture_update: re-sample the intensities of the template in use from confident frames (blended by
            ``texture_blend``). Off by default: every update copies the frame's estimate error into the
            template, which is what makes template-updating trackers drift.
        texture_blend: weight of the new sample in a texture update, in ``(0, 1]``.
        yaw_bin_deg, pitch_bin_deg: widths of the mosaic's pose bins (degrees).
        bin_centre_fraction: an entry is added only while the pose is within this fraction of a bin width of
            the bin's centre (so entries are built near the poses they are keyed by), in ``(0, 0.5]``.
        max_entries: the most entries a stream's mosaic holds (the reference included).
        switch_margin_deg: the tracker changes entry only when another is nearer (in yaw and pitch) than the
            current one by this much: hysteresis, so a head between two bins does not flip every frame.
        reference_radius_deg: within this (yaw, pitch) distance of the first frame's pose the tracker aligns
            against the reference entry even when another is nearer. The reference is the most exact template
            (its points and intensities carry no tracking or light-estimation error); other entries pay off
            where it has lost much of its visible surface. Measured at 640x480: with 20 degrees, the occlusion
            scenario (head up to 20 degrees from the first pose) aligned against a 15 degree entry while the
            occluder passed and diverged to 25 degrees (6.4 against the reference); with 30, pose_sweep's
            max error is 1.42 degrees (1.52 without the mosaic, 1.24 with no radius).
        normalised_size: side ``G`` of the normalised face the dissimilarity is measured on (pixels), >= 48: the
            default fiducial patches (11 px) found on a rendered face 0 of the 16 asked at 16 and 20 px, 1-2 at 24-40,
            3 at 48, 8 at the default 64; with none the confidence is 0 on every frame and a good track is
            declared lost.
        entry_stride: a new mosaic entry picks its finest level's points among the pixels on every
            ``entry_stride``-th row and column of the face's window (where that grid still holds four times the
            level's points; else every pixel), with the gradients and selection keys of the whole level. The
            finest level has some 20 000 candidate pixels for its 1500 points, so a sparser grid still draws them
            uniformly over the face; at 2, rasterizing and searching a quarter of the pixels took an entry from
            about 13 to 8 ms and template management from 3.5 to 3.0 ms per frame (benchmark.py's frames, one
            stream). It stays 1 (every pixel, as the first frame's template): at 2, scan_motion's max error was
            5.08 against 4.85 degrees (target 5), within the spread of drawing the points at all. Over three
            draws of the selection keys (``TrackerConfig.selection_seed`` 0, 1, 2; one thread), 1 against 2
            gave pose_sweep's mean 0.492 / 0.512 / 0.490 against 0.494 / 0.494 / 0.474 degrees and
            scan_motion's max 4.85 / 5.49 / 5.35 against 5.08 / 6.10 / 5.18: no accuracy difference either way,
            but the default's draw (seed 0) is the only one of the six runs that meets both targets.
        min_facing_cos: the normalised face keeps surface points facing the camera at least this much
            (cosine between the normal and the ray toward the camera). Oblique parts are resampled blurred and
            foreshortened and read as displaced patches: at 0.2 a right estimate at 30 degrees of yaw scored
            0.57 on a 320x240 render, at 0.6 it scores 0.92 (patches there are left out instead).
        dissimilarity: settings of the fiducial patches and their Lucas-Kanade (in pixels of the ``G`` face).
        confidence_threshold: a frame with dissimilarity confidence below this is not confident: nothing is
            learnt from it (no mosaic entry, no texture update) and it counts toward a loss. At most
            ``recover_confidence`` (refused above it: a frame between the two would count toward a loss and end
            it, and ``lost_after`` would never declare a stream scoring there lost); raise both together. At 0.5 the
            light_switch scenario (error about 1 degree, confidence 0.4-0.5 under the strongest light) was
            declared lost for 10 frames; at 0.3 never, while scan_motion's stretches above 5 degrees of error
            (confidence 0.04-0.2) still are.
        add_confidence: the confidence a frame needs for its templates to become a mosaic entry. The entry must
            also be within ``entry_reach`` bin widths (in yaw and pitch) of an existing entry: the mosaic grows
            outward from the first pose, each new entry judged against a reference seen from nearby. On a face
            unlike the model a right estimate scores less away from the reference's view: the James scan's
            long run scores 0.5-0.7 at its first bin centre (15 degrees of yaw, error under 1 degree). At 0.8 its
            mosaic never grew there, the confidence kept falling with the turn and the stream was marked lost at
            30-60 degrees with errors of 3-7 degrees (longest loss in view 105 frames), and ``scan_motion``'s max error
            was 5.5 degrees; at 0.75 entries are added (scan_motion max 4.85, mean 1.65; longest James loss 58).
            Lower, pose_sweep's mean error rose from 0.492 to 0.501-0.504 degrees (0.5, 0.65, 0.7: entries built
            from less exact frames) with no gain on scan_motion.
        entry_reach: see ``add_confidence``.
        lost_after: consecutive non-confident frames after which the stream is declared lost.
        very_low_confidence, lost_after_very_low: a stream is also lost after ``lost_after_very_low``
            consecutive frames below ``very_low_confidence``: a tracker left on the background when the face
            leaves the frame still fits its points there (the solve does not fail) but nothing of the face
            matches, and waiting ``lost_after`` frames would let it drift on.
        min_inside_fraction: a stream whose estimated face has fewer than this fraction of its vertices
            projecting inside the frame (or in front of the camera) is lost at once (the face left the frame).
        adopt_min_angle_deg: a lost stream goes on from a recovery candidate below ``recover_confidence`` when
            the candidate scores higher than the continued track and their rotations differ by more than this
            (the track has gone astray). Nearer, the continued track is kept: under an occluder both score
            near 0 and a candidate 8.6 degrees off once replaced a track 3.6 degrees off (occlusion scenario).
            A searched candidate must also lie within the searched depths (``search_depth_factors``, widened by
            10%): one whose solve ran to twice the depth replaced a track 5.6 degrees off (scan_motion without
            expression terms). A continued track whose face is out of the frame (``min_inside_fraction``) is no
            competitor: any candidate that passes its own checks (in the frame, within the searched depths) and is
            itself confident (``confidence_threshold``) replaces it, nearer than this or scoring less (a track on a
            face half out at the edge scored 0.95-0.98 on the patches still in view and kept a candidate on the
            face back in view, 0.90, from being adopted: the stream stayed LOST).
        adopt_min_confidence: and the candidate must score at least this. A candidate's solve that ran off
            the face scores near 0 (1e-4 and below), and so, beside a track judged lost, does a continued
            track that is right but seen from a view its reference does not cover: in benchmark.py's 32
            streams, right tracks 0.3-1 degree off at 40-45 degrees of yaw scored below 0.01 and were
            replaced by candidates 60-100 degrees off that scored 0.000 (the track's confidence was lower
            still). 0.01 is a mean patch displacement of about 2 d0 (1.6 px of the normalised face).
        recover_confidence: the confidence that ends a loss (from the continued track or a recovery); at least
            ``confidence_threshold`` (a loss holds until a frame clearly above it). A wrong
            placement scores near 0; a right one on a face unlike the model (the James scan) scores 0.6-0.7 near
            frontal, so 0.7 kept such a stream lost for tens of frames, and 0.3-0.45 at 45-50 degrees of yaw
            from its nearest entry, so 0.5 kept the James long run lost through a whole turn with errors of 4-5
            degrees (frames 2777-2866; 0.35: 2777-2800 and 2849-2866; both with ``add_confidence`` 0.5).
            A lost stream's continued track outside the searched depths (``search_depth_factors`` of its last
            confident depth, widened by 10%) scores 0, whatever its patches say: on the CANDIDE-3 long run with
            landmark-noise draw 2 (and README's per-unit shape prior with ``LookaheadConfig(min_keyframes=1,
            yaw_deg=10)``), lost under an occluder, the track drifted to twice the depth and 51 degrees
            off, scored 0.58 and ended the loss.
        recover_min_patches: a lost stream's continued track, and a recovery candidate, whose dissimilarity rests
            on fewer than this many present fiducial patches (:attr:`~torchface.template.dissimilarity.
            DissimilarityResult.present`, against the entry nearest it) scores 0: it neither ends the loss nor is
            adopted. 0 (the default) or 1: off. A profile entry's reference holds few textured patches (the
            James long run's -59 degree entry two, of which one was present), and a mean over one of them says
            nothing: there, with ``TrackerConfig(motion_prediction=0.5)``, a lost track 65-72 degrees off (the
            face taken for a profile with strong expression units) scored 0.47-0.82 on one patch, ended the loss
            and stayed successful for 18 frames (docs/limitations.md, "Fast motion"). Only lost streams
            are judged so: a right track at a turned pose keeps its confidence (a floor for every frame,
            ``DissimilarityConfig.min_present_fraction``, doubled the false losses at turned poses). Such a score
            counts as matching nothing for ``restart_after_unmatched`` too.
        recovery_every: a lost stream attempts a recovery when it is lost and then every this many frames (an
            attempt costs about three frames' time: the search, then a solve).
        restart_after_unmatched: with a detector, a lost stream starts afresh from the detector's landmarks
            (a new initialisation: templates, mosaic and reference from that frame) after this many recovery
            attempts in a row at which the detector found a face and neither its candidate nor the continued
            track scored ``adopt_min_confidence`` (a track out of the frame, under ``min_inside_fraction`` inside,
            counts as scoring nothing: its confidence is that of the patches still in view, 0.98 for a face half
            out at the edge), each showing the same face as the one before (its normalised
            face, placed by the detector's landmarks, matches the previous attempt's at ``confidence_threshold``;
            1: the first such attempt, unchecked): the face on screen is not the one the mosaic holds (a cut to
            another person, docs/limitations.md, "Hard cuts": both score 0.00, and the two attempts' faces
            match at 0.996). An occluder moving across the face does not count on (0.000-0.005). Without a
            detector it does nothing. Off (0) by default: a heavy occluder carried with the face does count on
            (320x240, half or three quarters of the face covered for 30 frames, the renderer's landmarks as the
            detector, 2: the stream restarted from the occluded face and was reported successful for 23 frames
            at confidence 0.86-1.00 drifting to 5 degrees off, then LOST once the occluder left, where without it
            those frames were LOST and it recovered 0.2 degrees off two frames after).
        conservative_when_unconfident: a stream whose last frame was not confident (below
            ``confidence_threshold``) is solved as a lost one is: the expression under the Gaussian prior, without
            the weak refinement prior and the sparsity (``track_step(conservative=)``). Off by default (lost
            streams only). With weak expression priors an occluder pushes the units before the stream is lost,
            and the pose follows them: with ``TrackerConfig(expression_quota=0.06, expression_sparsity=0.03)`` and
            the eyelid-keeping online start (docs/limitations.md, "Eyes closed") the first occluder of the
            CANDIDE-3 long run took 33 frames to recover from; with this on, 0.
        search_step_px: grid step of the mosaic search's first stage, pixels of the coarsest pyramid level
            halved once more (:func:`search_mosaic`). 2 finds faces the default grid misses, wrong placements too,
            at twice the cost (docs/limitations.md, Fast motion: measured on the long runs).
        plausible_turn_deg: ``(base, per_frame)``: a lost stream's pose must lie within ``base + per_frame * n``
            degrees of its last confident pose, ``n`` frames after it, or it scores 0 (the continued track) or is
            not adopted (a recovery candidate), as above: a head does not turn faster than that. ``(0, 0)`` (the
            default) turns the check off. ``(15, 1)`` with ``search_step_px`` 2 removed the CANDIDE-3 long run's
            wrong recovery (draw 0: a successful frame 62 degrees off, now 5) and left the other long runs as they
            were (landmark-noise draws 0-3; with the default grid, all of them).
        search_depth_factors: depths tried by the search, as factors of the last confident depth.
        search_depth_widening: from a loss's second recovery attempt on (without a detector), each search also
            tries ``search_depth_factors`` scaled by the next of these in turn, and a candidate found there may be
            adopted (its depth within the depths that attempt tried,
            widened by 10%). Without it a face that came back nearer or farther than 0.77-1.32 times its last
            confident depth was never found again (a face leaving the frame and returning at 1.6 or 0.6 times
            its depth stayed lost to the end). Empty: the searched depths stay ``search_depth_factors``.
        search_points: template points per entry used by the search (a uniform subset).
        search_min_inside: a placement needs this fraction of its points inside the image.
        clean_radius_deg: a stream whose pose is within this (yaw, pitch) distance of the pose its mosaic entry
            was built at, on a clean frame (``clean_rejected_fraction``), is solved with a Huber loss at the
            finest pose level instead of the tracker's Tukey loss (same constant). Near the template's own view
            the residual of a clean frame is appearance misfit (a face unlike the model under a changed light),
            which Tukey's down-weighting of 2-4.7 scale residuals turns into a pose bias; away from it, Tukey's
            rejections of view-dependent misfit (self-occlusion, silhouettes) help. Measured with evaluate.py:
            the James scan's returns to frontal went from 1.43 / 1.44 degrees (frames 405, 2700; solving them
            from the first frame's pose gave the same: the minimum of the Tukey cost) to 0.67 / 0.76, max over
            the 13 returns 1.44 -> 0.84; CANDIDE-3's 0.61 -> 0.64. The mean errors of the standard scenarios
            moved by at most 0.012 degree (pose_sweep 0.483 -> 0.494). Huber at every clean frame instead (no
            radius) gave the same returns but took pose_sweep to 0.53 and scan_motion from 1.88 to 2.08 degrees
            mean; a radius of 5 degrees took pose_sweep to 0.497 and failed a small-face known-answer test of
            ``training_hooks``. 0 turns the rule off. Its cost is within the noise: 32 streams of benchmark.py's
            frames, on and off alternating in one process, took 17.0-17.9 against 17.0-17.7 ms per stream-frame
            (the managed solve 13.3-14.0 against 13.8-13.9, the same iterations). A slower managed solve measured
            in separate benchmark.py runs (16.4 against 11.8 ms) did not reproduce in one process.
        clean_rejected_fraction: a frame is clean for a stream when its middle pyramid level ended with fewer
            than this fraction of its valid points rejected (zero Tukey weight at that level's robust scale).
            Measured: 0-0.5% at the James returns, 1.4-7.6% under the ``occlusion`` scenario's occluder.
    """

    enabled: bool = True
    mosaic: bool = True
    texture_update: bool = False
    texture_blend: float = 0.5
    yaw_bin_deg: float = 15.0
    pitch_bin_deg: float = 15.0
    bin_centre_fraction: float = 0.25
    max_entries: int = 16
    switch_margin_deg: float = 2.0
    reference_radius_deg: float = 30.0
    normalised_size: int = 64
    entry_stride: int = 1
    min_facing_cos: float = 0.6
    dissimilarity: DissimilarityConfig = field(default_factory=_default_dissimilarity)
    confidence_threshold: float = 0.3
    add_confidence: float = 0.75
    entry_reach: float = 1.5
    lost_after: int = 15
    very_low_confidence: float = 0.1
    lost_after_very_low: int = 3
    min_inside_fraction: float = 0.6
    adopt_min_angle_deg: float = 15.0
    adopt_min_confidence: float = 0.01
    recover_confidence: float = 0.35
    recovery_every: int = 5
    recover_min_patches: int = 0
    restart_after_unmatched: int = 0
    search_step_px: float = 3.0
    search_depth_factors: tuple[float, ...] = (0.85, 1.0, 1.2)
    search_depth_widening: tuple[float, ...] = (0.7, 1.45, 0.5, 2.0)
    search_points: int = 300
    search_min_inside: float = 0.8
    clean_radius_deg: float = 3.0
    clean_rejected_fraction: float = 0.01
    conservative_when_unconfident: bool = False
    plausible_turn_deg: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("enabled", "mosaic", "texture_update", "conservative_when_unconfident"):
            object.__setattr__(self, name, check_bool(getattr(self, name), name))
        if not isinstance(self.dissimilarity, DissimilarityConfig):
            raise TypeError(f"dissimilarity must be a DissimilarityConfig, got {type(self.dissimilarity).__name__}")
        # Each number's range, stated once (check_number: "0.5" was "'<' not supported", NaN passed "< 0" checks,
        # inf ">0" and ">= 0" ones: search_step_px inf made an empty coarse grid and a fine one int(inf) wide)
        for name, interval in (
            ("texture_blend", "(0, 1]"), ("yaw_bin_deg", "(0, inf)"), ("pitch_bin_deg", "(0, inf)"),
            ("bin_centre_fraction", "(0, 0.5]"), ("switch_margin_deg", "[0, inf)"), ("reference_radius_deg", "[0, inf)"),
            ("min_facing_cos", "[0, 1]"), ("confidence_threshold", "[0, 1]"), ("add_confidence", "[0, 1]"),
            ("entry_reach", "(0, inf)"), ("very_low_confidence", "[0, 1]"), ("min_inside_fraction", "[0, 1]"),
            ("adopt_min_angle_deg", "[0, inf)"), ("adopt_min_confidence", "[0, 1]"), ("recover_confidence", "[0, 1]"),
            ("search_step_px", "(0, inf)"), ("search_min_inside", "[0, 1]"), ("clean_radius_deg", "[0, inf)"),
            ("clean_rejected_fraction", "[0, 1]"),
        ):  # fmt: skip
            object.__setattr__(self, name, check_number(getattr(self, name), name, interval))
        for name, low in (("max_entries", 1), ("normalised_size", None), ("entry_stride", 1), ("lost_after", 1),
                          ("lost_after_very_low", 1), ("recovery_every", 1), ("search_points", 8),
                          ("restart_after_unmatched", 0), ("recover_min_patches", 0)):  # fmt: skip
            object.__setattr__(self, name, check_int(getattr(self, name), name, low))
        # A stream is lost after lost_after frames below confidence_threshold, and the loss ends at a frame reaching
        # recover_confidence (managed_step): with confidence_threshold above it, a frame between the two counted
        # toward the loss and ended it at once, so lost_after did nothing (confidence_threshold=0.99, lost_after=1:
        # status 0 at confidence 0.56 on every frame). The default (0.3, 0.35) holds a loss until a frame clearly
        # above the threshold.
        if self.confidence_threshold > self.recover_confidence:
            raise ValueError(
                f"confidence_threshold ({self.confidence_threshold:g}) must not exceed recover_confidence "
                f"({self.recover_confidence:g}): a frame scoring between them counts toward a loss and ends it, so "
                f"lost_after would never declare a stream scoring there lost; raise recover_confidence with it, e.g. "
                f"TemplateConfig(confidence_threshold={self.confidence_threshold:g}, "
                f"recover_confidence={self.confidence_threshold:g})"
            )
        if self.normalised_size < 48:
            raise ValueError(f"normalised_size must be >= 48 (smaller faces hold too few fiducial patches for a "
                             f"confidence), got {self.normalised_size}")  # fmt: skip
        turn = tuple(float(v) for v in check_reals(self.plausible_turn_deg, "plausible_turn_deg", "[0, inf)"))
        if len(turn) != 2:  # (b"11": two 49s, refused by check_reals)
            raise ValueError(f"plausible_turn_deg must be two values (base, per frame), got {self.plausible_turn_deg}")
        object.__setattr__(self, "plausible_turn_deg", turn)
        for name in ("search_depth_factors", "search_depth_widening"):  # (strings: "'>' not supported"; bools: 1)
            object.__setattr__(self, name, check_reals(getattr(self, name), name, "(0, inf)"))
        if not self.search_depth_factors:
            raise ValueError("search_depth_factors must be positive factors, got ()")

    def depth_scale(self, attempts: int) -> float:
        """The factor a recovery attempt scales ``search_depth_factors`` by besides 1, after ``attempts`` attempts
        in the same loss: 1.0 (none) for the first, then ``search_depth_widening`` in turn."""
        n = int(attempts)
        if n < 1 or not self.search_depth_widening:
            return 1.0
        return float(self.search_depth_widening[(n - 1) % len(self.search_depth_widening)])


@dataclass(frozen=True, eq=False)
class MosaicLevel:
    """One pyramid level of every entry, compact (:func:`entry_templates` rebuilds full templates).

    Attributes:
        face_index: ``(B, E, N)`` int64 triangle of each point.
        bary: ``(B, E, N, 3)`` barycentric coordinates in it.
        intensity: ``(B, E, N)`` gray value under the reference light.
        valid: ``(B, E, N)`` bool (False in unused point slots; an unused entry's values are not defined:
            see :class:`Mosaic`).
    """

    face_index: Tensor
    bary: Tensor
    intensity: Tensor
    valid: Tensor

    def select(self, index: Tensor) -> "MosaicLevel":
        """The streams ``index`` (a ``(B',)`` int64 or bool tensor)."""
        return MosaicLevel(*(getattr(self, f.name)[index] for f in fields(MosaicLevel)))


@dataclass(frozen=True, eq=False)
class Mosaic:
    """The templates of every stream keyed by head pose (module docstring).

    Attributes:
        levels: one :class:`MosaicLevel` per pyramid level, finest first.
        rotation: ``(B, E, 3, 3)`` the head pose each entry was built at.
        ypr_deg: ``(B, E, 3)`` the same as yaw, pitch, roll in degrees (``matrix_to_euler(rotation)``, kept so
            that choosing an entry each frame does not convert every entry's rotation again).
        bins: ``(B, E, 2)`` int64 (yaw, pitch) bin of each entry, counted from the reference entry's pose
            (:func:`pose_bins` with ``origin_deg = ypr_deg[:, 0]``; entry 0 is bin ``(0, 0)``).
        used: ``(B, E)`` bool, the entry slot is filled; entry 0 (the reference) always is.
        references: the entries' dissimilarity references: a
            :class:`~torchface.template.dissimilarity.DissimilarityReference` whose tensors have the entry
            dimension after the batch (``image (B, E, 1, G, G)``, ...); ``references.select((streams,
            entries))`` gives the ``(B', ...)`` reference of entry ``entries[i]`` of stream ``streams[i]``.
        claimed: ``(B, E)`` bool or None, bookkeeping of :func:`add_entries` (not part of the mosaic's value):
            the entry slots ever written in the storage of ``levels`` and ``references``, which this mosaic may
            share with the mosaics it was made from or that were made from it. None: not known (the next
            :func:`add_entries` copies the storage).

    Only the used entries' data is defined: an unused slot of ``levels`` and ``references`` may hold an entry
    that a mosaic made later from this one added there (they share storage; see :func:`add_entries`).
    """

    levels: tuple[MosaicLevel, ...]
    rotation: Tensor
    ypr_deg: Tensor
    bins: Tensor
    used: Tensor
    references: DissimilarityReference
    claimed: Tensor | None = field(default=None, repr=False, compare=False)

    @property
    def num_entries(self) -> Tensor:
        """``(B,)`` entries per stream."""
        return self.used.sum(-1)

    @property
    def capacity(self) -> int:
        """``E``, entry slots allocated per stream: at least the most entries a stream holds, and more after
        :func:`add_entries` grew the storage by several slots (the slots beyond a stream's entries are unused)."""
        return int(self.used.shape[1])

    def select(self, index: Tensor) -> "Mosaic":
        """The mosaics of streams ``index`` (a ``(B',)`` int64 or bool tensor), in new storage of their own (so
        ``claimed`` is their used entries, as after a copy in :func:`add_entries`)."""
        used = self.used[index]
        return Mosaic(
            tuple(lv.select(index) for lv in self.levels), self.rotation[index], self.ypr_deg[index],
            self.bins[index], used, self.references.select(index), used.clone(),
        )  # fmt: skip


def pose_bins(ypr_deg: Tensor, config: TemplateConfig, origin_deg: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``(B, 3)`` yaw/pitch/roll (degrees) -> ``(B, 2)`` int64 (yaw, pitch) bins and ``(B,)`` "near the centre".

    Bin ``k`` covers ``[(k - 1/2) w, (k + 1/2) w)`` of the angle less the origin's, for bin width ``w``; "near
    the centre" is within ``config.bin_centre_fraction * w`` of ``k w`` on both axes. Roll is ignored: it turns
    the face in the image plane and changes no part's visibility.

    Args:
        ypr_deg: ``(B, 3)`` the poses.
        config: the bin widths and centre fraction.
        origin_deg: ``(B, 3)`` the pose of bin ``(0, 0)``'s centre (roll ignored); None for the camera's axis.
            The mosaic keys its entries relative to its reference entry's pose (:class:`Mosaic`).
    """
    widths = ypr_deg.new_tensor([config.yaw_bin_deg, config.pitch_bin_deg])
    angles = ypr_deg[:, :2] if origin_deg is None else ypr_deg[:, :2] - origin_deg[:, :2]
    scaled = angles / widths
    bins = torch.floor(scaled + 0.5)
    near = ((scaled - bins).abs() <= config.bin_centre_fraction).all(-1)
    return bins.to(torch.int64), near


def frame_dissimilarity(
    frames: Tensor,
    model: FaceModel,
    layout: NormalisedFaceLayout,
    reference: DissimilarityReference,
    shape_coeffs: Tensor,
    anim_coeffs: Tensor,
    axis_angle: Tensor,
    translation: Tensor,
    illumination: Tensor,
    intrinsics: Intrinsics,
    config: TemplateConfig,
    rotation: Tensor | None = None,
    verts_cam: Tensor | None = None,
    backend: Backend = Backend.AUTO,
) -> DissimilarityResult:
    """Dissimilarity and confidence of each frame's estimate against the reference (Section 4.1).

    Args:
        frames: ``(B, 3, H, W)`` in [0, 1]; shape_coeffs ``(B, S)``, anim_coeffs ``(B, A)``, axis_angle
            ``(B, 3)``, translation ``(B, 3)`` mm, illumination ``(B, L)``: the estimate.
        layout: :func:`~torchface.normalise.build_normalised_layout` of ``config.normalised_size``.
        reference: :func:`~torchface.template.dissimilarity.build_dissimilarity_reference` of a reference
            frame's normalised face made the same way (:func:`reference_face`).
        rotation: ``(B, 3, 3)`` the matrix of ``axis_angle`` when the caller has it (None: computed).
        verts_cam: ``(B, V, 3)`` the estimate's posed vertices (camera frame, mm) when the caller has them (e.g.
            shared with :func:`face_inside_fraction`); the parameters' shapes are then not checked again.
        backend: of the smoothing and patch tracking (:func:`~torchface.template.dissimilarity.dissimilarity`).

    Returns:
        :class:`~torchface.template.dissimilarity.DissimilarityResult` (``dissimilarity (B,)`` in pixels of the
        normalised face, ``confidence (B,)`` in [0, 1]).
    """
    image, mask = reference_face(
        frames, model, layout, shape_coeffs, anim_coeffs, axis_angle, translation, illumination, intrinsics, config,
        rotation=rotation, verts_cam=verts_cam, backend=backend,
    )  # fmt: skip
    return dissimilarity(reference, image, mask, backend=backend)


def reference_face(
    frames: Tensor, model: FaceModel, layout: NormalisedFaceLayout, shape_coeffs: Tensor, anim_coeffs: Tensor,
    axis_angle: Tensor, translation: Tensor, illumination: Tensor, intrinsics: Intrinsics, config: TemplateConfig,
    rotation: Tensor | None = None, verts_cam: Tensor | None = None, backend: Backend = Backend.AUTO,
) -> tuple[Tensor, Tensor]:
    """The normalised face ``(B, 3, G, G)`` and mask ``(B, 1, G, G)`` of a frame as template management makes it:
    a reference frame's, and every later frame's in :func:`frame_dissimilarity` (arguments as there; ``backend``
    of the sampling, :func:`~torchface.normalise.normalised_face_posed`). The frames' values are not checked here
    (the tracker's steps check them)."""
    if verts_cam is None:
        face = normalised_face(
            frames, model, layout, shape_coeffs, anim_coeffs, axis_angle, translation, illumination, intrinsics,
            min_facing_cos=config.min_facing_cos, zbuffer=False, rotation=rotation, backend=backend, check_values=False,
        )  # fmt: skip
    else:
        face = normalised_face_posed(frames, model, layout, verts_cam, illumination, intrinsics,
                                     min_facing_cos=config.min_facing_cos, zbuffer=False, backend=backend,
                                     check_values=False)  # fmt: skip
    return face.image, face.mask


def light_normalised_intensity(intensity: Tensor, normals: Tensor, rotation: Tensor, illumination: Tensor) -> Tensor:
    """``(B, N)`` template intensities brought back to the reference light (inverse of Eq. 19).

    Args:
        intensity: ``(B, N)`` as seen under ``illumination``; normals: ``(B, N, 3)`` the points' head-frame
            normals (:attr:`~torchface.template.points.Template.normals`, or
            :func:`~torchface.template.points.point_normals`); rotation ``(B, 3, 3)`` the pose they were seen
            at (the normals are rotated into the camera frame as the solver's illumination basis does);
            illumination ``(B, L)``.
    """
    normals_cam = torch.matmul(normals, rotation.transpose(1, 2))
    return remove_illumination(intensity, normals_cam, illumination)


def _entry_level(t: Template) -> MosaicLevel:
    """A one-entry mosaic level holding ``t``'s compact form: copies, not views, so that a template written in
    place (``managed_step(donate=True)``) never changes a stored entry."""
    return MosaicLevel(*(x.unsqueeze(1).clone() for x in (t.face_index, t.bary, t.intensity, t.valid)))


def new_mosaic(
    templates: tuple[Template, ...], rotation: Tensor, ypr_deg: Tensor, reference: DissimilarityReference,
    config: TemplateConfig,
) -> Mosaic:
    """A mosaic whose only entry (0) is each stream's reference templates (seen under the reference light).

    Args:
        templates: per level, finest first, batch ``B``; rotation ``(B, 3, 3)`` and ypr_deg ``(B, 3)`` the pose
            they were built at; reference: the dissimilarity reference of that frame (batch ``B``).

    The mosaic keeps a copy of ``rotation`` (it kept a view: the first result's, which its caller may modify).
    """
    bins, _ = pose_bins(ypr_deg, config, origin_deg=ypr_deg)  # the reference is bin (0, 0)
    B = rotation.shape[0]
    return Mosaic(
        tuple(_entry_level(t) for t in templates), rotation.unsqueeze(1).clone(), matrix_to_euler(rotation).unsqueeze(1),
        bins.unsqueeze(1),
        torch.ones(B, 1, dtype=torch.bool, device=rotation.device), _map_reference(reference, lambda x: x.unsqueeze(1)),
    )  # fmt: skip


def _reference_tensors(ref: DissimilarityReference) -> list[Tensor]:
    """``ref``'s tensors in field order, its Lucas-Kanade side last (the order :func:`_map_reference` visits)."""
    return [ref.image, ref.mask, ref.centres, ref.patch_valid, ref.score] + ([] if ref.lk is None else list(ref.lk))


def _map_reference(ref: DissimilarityReference, fn) -> DissimilarityReference:
    """``ref`` with ``fn`` applied to every tensor, in :func:`_reference_tensors` order."""
    out = [fn(x) for x in _reference_tensors(ref)]
    lk = None if ref.lk is None else type(ref.lk)(*out[5:])
    return DissimilarityReference(out[0], out[1], out[2], out[3], out[4], ref.config, lk)


#: The most entry slots :func:`add_entries` grows a mosaic by at once (:func:`_grown_capacity`).
_GROWTH_CHUNK = 4


def _grown_capacity(capacity: int, need: int, limit: int | None) -> int:
    """The entry slots a mosaic of ``capacity`` slots grows to when an entry needs ``need > capacity``: doubled, by
    at most :data:`_GROWTH_CHUNK` slots, and not beyond ``limit`` (None: no limit), but at least ``need``.

    Growing copies every per-entry tensor of the mosaic (levels, references, poses) into new memory. Grown one slot
    at a time, benchmark.py's 32 streams (117 steps, 11 entries at most, one thread) grew it 10 times, 2-14 ms each
    (58-65 ms in all); grown so, 4 times (42-44 ms in all; entries written into slots grown before cost what
    the others do, 0.7 ms a call). The cost: at most ``_GROWTH_CHUNK - 1`` unused slots per stream (0.16 MB each
    at the default sizes; there 12 slots, 60 MB, against 11, 55 MB), and with ``limit``
    (``TemplateConfig.max_entries``) no more slots than one at a time makes when the mosaics fill up."""
    grown = capacity + min(max(capacity, 1), _GROWTH_CHUNK)
    if limit is not None:
        grown = min(grown, limit)
    return max(grown, need)


def _grow(mosaic: Mosaic, extra: int) -> Mosaic:
    """The mosaic with ``extra`` more (unused) entry slots per stream."""
    def pad(x: Tensor, value: float | bool = 0) -> Tensor:
        shape = list(x.shape)
        shape[1] = extra
        return torch.cat([x, x.new_full(shape, value)], dim=1)

    levels = tuple(MosaicLevel(pad(lv.face_index), pad(lv.bary), pad(lv.intensity), pad(lv.valid, False))
                   for lv in mosaic.levels)  # fmt: skip
    eye = torch.eye(3, dtype=mosaic.rotation.dtype, device=mosaic.rotation.device)
    rot = torch.cat([mosaic.rotation, eye.expand(mosaic.rotation.shape[0], extra, 3, 3)], dim=1)
    refs = _map_reference(mosaic.references, lambda x: pad(x, False) if x.dtype == torch.bool else pad(x))
    return Mosaic(levels, rot, pad(mosaic.ypr_deg), pad(mosaic.bins), pad(mosaic.used, False), refs)


def add_entries(
    mosaic: Mosaic, streams: Tensor, templates: tuple[Template | TemplatePixels, ...], rotation: Tensor,
    bins: Tensor, reference: DissimilarityReference, max_capacity: int | None = None,
) -> tuple[Mosaic, Tensor]:
    """Store one new entry for each of ``streams`` in its first free slot (a rare event: not in the hot path).

    Args:
        mosaic: batch ``B``.
        streams: ``(B',)`` int64 distinct stream indices.
        templates: per level, batch ``B'``, intensities already under the reference light (only the compact
            form is stored: a :class:`~torchface.template.points.TemplatePixels` is enough).
        rotation: ``(B', 3, 3)`` and bins ``(B', 2)``: the pose the templates were built at.
        reference: batch ``B'``, the dissimilarity reference of the frame they were built from.
        max_capacity: where the mosaic has no free slot for an entry, it grows by several slots at once
            (doubled, by at most 4: :func:`_grown_capacity`), to at most this many (unless the entries need more;
            :attr:`TemplateConfig.max_entries`, the most a stream may hold); None: no limit.

    Returns:
        The new mosaic and ``(B',)`` the entry index each stream's entry got. Its tensors are normal tensors even
        when this runs in inference mode (a tracking step's): they persist in the tracker's state, which would
        otherwise copy them again on the way out (:mod:`torchface.tracker.inference`; 54 MB per step at 32 streams).

    ``mosaic`` is not changed (its used entries keep their values, its ``used`` and poses are its own). The large
    per-entry tensors (``levels``, ``references``) are written in place, shared with ``mosaic``, where the slots
    written have never been written in that storage (:attr:`Mosaic.claimed`) and no gradient is involved; else
    they are copied first (copying the whole mosaic took 5 ms per added entry at 32 streams). So a second entry
    added from the same ``mosaic`` (a branch) copies rather than overwrite the first.
    """
    # (a count: "16" was a TypeError from inside the growth, "'<' not supported between instances of 'str' and 'int'")
    max_capacity = check_optional_int(max_capacity, "max_capacity", 1)
    with torch.inference_mode(False):
        return _add_entries(mosaic, streams, templates, rotation, bins, reference, max_capacity)


def _add_entries(
    mosaic: Mosaic, streams: Tensor, templates: tuple[Template | TemplatePixels, ...], rotation: Tensor,
    bins: Tensor, reference: DissimilarityReference, max_capacity: int | None,
) -> tuple[Mosaic, Tensor]:
    slot = mosaic.num_entries[streams]
    need = int(slot.max()) + 1 if streams.numel() else 0
    claimed = mosaic.claimed
    if need > mosaic.capacity:  # new storage, this mosaic's alone
        mosaic = _grow(mosaic, _grown_capacity(mosaic.capacity, need, max_capacity) - mosaic.capacity)
        claimed = mosaic.used.clone()
    new_ref = _reference_tensors(reference)
    names = [f.name for f in fields(MosaicLevel)]  # a template holds the same fields (and more)
    storage = [getattr(lv, name) for lv in mosaic.levels for name in names] + _reference_tensors(mosaic.references)
    values = [getattr(t, name) for t in templates for name in names] + new_ref
    in_place = (
        claimed is not None and not bool(claimed[streams, slot].any())
        and not any(x.requires_grad or x.is_inference() for x in storage)
        and not any(x.requires_grad for x in values)
    )  # fmt: skip
    if not in_place or claimed is None:  # (in place implies claimed)
        storage = [x.clone() for x in storage]
        claimed = mosaic.used.clone()
    for x, v in zip(storage, values):
        x[streams, slot] = _of_dtype(v, x.dtype)
    claimed[streams, slot] = True
    parts = iter(storage)
    levels = tuple(MosaicLevel(*(next(parts) for _ in names)) for _ in mosaic.levels)
    refs = _map_reference(mosaic.references, lambda _: next(parts))
    rot = mosaic.rotation.clone()
    rot[streams, slot] = rotation.to(rot.dtype)
    ypr = mosaic.ypr_deg.clone()
    ypr[streams, slot] = matrix_to_euler(rot[streams, slot])
    b = mosaic.bins.clone()
    b[streams, slot] = bins
    used = mosaic.used.clone()
    used[streams, slot] = True
    return Mosaic(levels, rot, ypr, b, used, refs, claimed), slot


def within_reach(mosaic: Mosaic, ypr_deg: Tensor, config: TemplateConfig) -> Tensor:
    """``(B,)`` bool: the pose ``ypr_deg (B, 3)`` is within ``config.entry_reach`` bin widths of a used entry."""
    widths = ypr_deg.new_tensor([config.yaw_bin_deg, config.pitch_bin_deg])
    entry_ypr = mosaic.ypr_deg[..., :2]  # (B, E, 2)
    d = ((entry_ypr - ypr_deg[:, None, :2]) / widths).abs().amax(-1)
    return ((d <= config.entry_reach) & mosaic.used).any(-1)


def has_bin(mosaic: Mosaic, bins: Tensor, streams: Tensor | None = None) -> Tensor:
    """``(B,)`` bool: the stream's mosaic already has an entry in bin ``bins (B, 2)``; with ``streams (B',)``
    (int64), the streams ``streams[i]`` for ``bins (B', 2)``."""
    entry_bins, used = mosaic.bins, mosaic.used
    if streams is not None:
        entry_bins, used = entry_bins[streams], used[streams]
    return ((entry_bins == bins.unsqueeze(1)).all(-1) & used).any(-1)


def _entry_distances(mosaic: Mosaic, ypr_deg: Tensor, streams: Tensor | None) -> Tensor:
    """``(B, E)`` (yaw, pitch) distances (degrees) of ``ypr_deg (B, 3)`` to the streams' entries, inf where unused."""
    entry_ypr, used = mosaic.ypr_deg, mosaic.used  # (B, E, 3), (B, E)
    if streams is not None:
        entry_ypr, used = entry_ypr[streams], used[streams]
    d = (entry_ypr[..., :2] - ypr_deg[:, None, :2]).norm(dim=-1)
    return torch.where(used, d, float("inf"))


def nearest_entries(mosaic: Mosaic, ypr_deg: Tensor, streams: Tensor | None = None) -> Tensor:
    """``(B,)`` the entry nearest each pose in (yaw, pitch), the lowest index on a tie (entry 0 first):
    :func:`select_entries` with no margin, no reference radius and entry 0 as the current one.

    Args:
        ypr_deg: ``(B, 3)`` poses; streams: ``(B,)`` int64 the mosaic rows of a sub-batch, or None for all.
    """
    return _entry_distances(mosaic, ypr_deg, streams).argmin(-1)


def select_entries(
    mosaic: Mosaic,
    ypr_deg: Tensor,
    current: Tensor,
    margin_deg: float,
    reference_radius_deg: float = 0.0,
    streams: Tensor | None = None,
) -> Tensor:
    """``(B,)`` the entry each stream aligns against next: the nearest in (yaw, pitch), with hysteresis.

    Args:
        ypr_deg: ``(B, 3)`` the current pose estimate; current: ``(B,)`` int64 the entry in use.
        margin_deg: the current entry is kept unless another is nearer by more than this
            (:attr:`TemplateConfig.switch_margin_deg`; 0 picks the nearest).
        reference_radius_deg: within this distance of the reference entry (0) it is used whatever else is
            nearer (:attr:`TemplateConfig.reference_radius_deg`); a stream on another entry comes back to it
            once ``margin_deg`` inside.
        streams: ``(B,)`` int64 the mosaic rows of a sub-batch, or None for all.
    """
    d = _entry_distances(mosaic, ypr_deg, streams)
    best = d.argmin(-1)
    d_cur = d.gather(1, current.unsqueeze(1)).squeeze(1)
    d_best = d.gather(1, best.unsqueeze(1)).squeeze(1)
    choice = torch.where(d_best + margin_deg < d_cur, best, current)
    d_ref = d[:, 0]
    use_ref = (d_ref <= reference_radius_deg) & ((current == 0) | (d_ref <= reference_radius_deg - margin_deg))
    return torch.where(use_ref, torch.zeros_like(choice), choice)


def entry_templates(
    model: FaceModel, shape_coeffs: Tensor, mosaic: Mosaic, streams: Tensor, entries: Tensor,
    backend: Backend = Backend.AUTO,
) -> tuple[Template, ...]:
    """The full templates (every level) of entry ``entries[i]`` of stream ``streams[i]``.

    Args:
        shape_coeffs: ``(B', S)`` the streams' shape units; streams, entries: ``(B',)`` int64.
        backend: of :func:`~torchface.template.points.template_at`.

    Returns:
        One :class:`Template` per level with batch ``B'``.
    """
    verts = model.deform(shape_coeffs, None)
    neutral = verts, vertex_normals(verts, model.faces)  # the person's, once for every level
    # Every level's points in one template_at call (its work is per point: the same values as level by level, in
    # one set of operations instead of one per level; 2.1-2.3 against 2.8-2.9 ms for one stream).
    sizes = [lv.face_index.shape[-1] for lv in mosaic.levels]

    def joined(name: str) -> Tensor:
        return torch.cat([getattr(lv, name)[streams, entries] for lv in mosaic.levels], 1)

    levels = [tuple(getattr(lv, name)[streams, entries] for name in ("face_index", "bary", "intensity", "valid"))
              for lv in mosaic.levels]  # fmt: skip
    if use_native(backend, (neutral[0], levels[0][1]), "template"):  # level by level: each with its point-last copies
        return tuple(template_at(model, shape_coeffs, *lv, neutral=neutral, backend=backend) for lv in levels)
    whole = template_at(model, shape_coeffs, joined("face_index"), joined("bary"), joined("intensity"),
                        joined("valid"), neutral=neutral, backend=Backend.TORCH)  # fmt: skip
    parts = [getattr(whole, f.name).split(sizes, 1) for f in fields(Template)]
    return tuple(Template(*(p[i].contiguous() for p in parts)) for i in range(len(sizes)))


def face_inside_fraction(model: FaceModel, verts_cam: Tensor, intrinsics: Intrinsics) -> Tensor:
    """``(B,)`` fraction of the model's surface vertices in front of the camera and projecting inside the frame.

    Args:
        verts_cam: ``(B, V, 3)`` the posed vertices (camera frame, mm).
    """
    v = verts_cam[:, model.surface_vertex_mask]
    uv = project_points(v, intrinsics)
    W, H = intrinsics.width, intrinsics.height
    ok = (v[..., 2] > 1.0) & (uv[..., 0] >= 0) & (uv[..., 0] <= W - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= H - 1)
    return ok.to(verts_cam.dtype).mean(-1)


def _native_layout_constants(model: FaceModel, layout: NormalisedFaceLayout, dtype: torch.dtype) -> tuple[Tensor, ...]:
    """The model's and the layout's tensors the native confidence reads, contiguous in ``dtype`` (int64 indices,
    the surface mask as bytes): made once per layout, model and dtype and kept on the layout, one set per dtype,
    made again for another model object (a ``FaceTracker.to()`` that changes nothing, as a parent module's
    ``.to(device)`` before each training step, makes a new one each time: one set per model piled up)."""
    cache = layout.__dict__.setdefault("_native_constants", {})
    held = cache.get(dtype)
    if held is None or held[-1] is not model:  # (the model held too: compared by identity, not by a reusable id)
        with torch.inference_mode(False):
            cache[dtype] = (
                model.mean.to(dtype).contiguous(), model.shape_units.to(dtype).contiguous(),
                model.animation_units.to(dtype).contiguous(), model.faces.to(torch.int64).contiguous(),
                model.surface_vertex_mask.to(torch.uint8).contiguous(), layout.face_index.to(torch.int64).contiguous(),
                layout.pixel_index.to(torch.int64).contiguous(), layout.bary.to(dtype).contiguous(), model,
            )  # fmt: skip
    return cache[dtype]


@functools.lru_cache(maxsize=16)
def _flat_kernel(sigma: float, dtype: torch.dtype) -> Tensor:
    """The native confidence's smoothing kernel on the CPU: :func:`~torchface.template.dissimilarity._gaussian_kernels`'
    1D Gaussian of ``sigma`` as a contiguous ``(k,)`` tensor (``(1,)`` ones without smoothing, ``sigma <= 0``): a
    cached constant, made outside inference mode (it was a reshape of the cached kernel at every call)."""
    with torch.inference_mode(False):
        if sigma <= 0:
            return torch.ones(1, dtype=dtype)
        return _gaussian_kernels(sigma, dtype, torch.device("cpu"))[0].reshape(-1).contiguous()


def native_mosaic_confidence(
    frames: Tensor, model: FaceModel, layout: NormalisedFaceLayout, mosaic: "Mosaic", rows: Tensor,
    ypr_deg: Tensor | None, shape_coeffs: Tensor, anim_coeffs: Tensor, rotation: Tensor, translation: Tensor,
    illumination: Tensor, intrinsics: Intrinsics, config: TemplateConfig, backend: Backend,
) -> tuple[Tensor, Tensor, Tensor, tuple[Tensor, Tensor], Tensor] | None:
    """The per-frame confidence of template management in one native pass per stream (``_native/confidence.h``):
    the mesh posed at the estimate, the mosaic entry nearest its (yaw, pitch) (:func:`nearest_entries`),
    :func:`reference_face` (no z-buffer), :func:`~torchface.template.dissimilarity.dissimilarity` against that
    entry's reference, and :func:`face_inside_fraction`; the torch code's values to rounding
    (tests/tracker/test_native.py).

    Args:
        frames: ``(B, C, H, W)``; rows: ``(B,)`` int64 the streams' rows of ``mosaic``; ypr_deg: ``(B, 3)`` the
            estimate's yaw/pitch/roll (None: entry 0 for every stream); shape_coeffs ``(B, S)``, anim_coeffs
            ``(B, A)``, rotation ``(B, 3, 3)``, translation ``(B, 3)``, illumination ``(B, L)``: the estimate.

    Returns:
        ``(dissimilarity (B,), confidence (B,), inside (B,), (image (B, C, G, G), mask (B, 1, G, G)), entry (B,))``,
        or None where the native kernel cannot run and ``backend`` lets the torch code run instead
        (:func:`~torchface.backend.use_native`; a reference without precomputed patches counts as unsuitable).
    """
    from torchface import _native

    refs = mosaic.references
    lk = refs.lk
    dtype = rotation.dtype
    if lk is None or lk.template.shape[-1] != 1 or lk.template.dtype != dtype:
        if backend is Backend.NATIVE:
            raise RuntimeError("the native confidence needs the mosaic's references with their gray patches")
        return None
    if not use_native(backend, (frames, rotation, translation, anim_coeffs, illumination, lk.template), "confidence"):
        return None
    B, C, H, W = frames.shape
    G = layout.size
    cam = check_intrinsics(intrinsics)
    dc = refs.config
    mean, shape_units, anim_units, faces, surface, face_index, pixel_index, bary, _ = _native_layout_constants(
        model, layout, dtype
    )
    grid, template, sd, ref_weight, ref_total = (x.contiguous() for x in lk)
    E, K, n = grid.shape[1:4]
    sigma = float(dc.smoothing_sigma)
    kernel = _flat_kernel(sigma, dtype)
    inputs = [x.contiguous() for x in (_of_dtype(shape_coeffs, dtype), anim_coeffs, rotation, translation, frames,
                                       illumination, rows, _of_dtype(mosaic.ypr_deg, dtype), mosaic.used,
                                       refs.patch_valid)]  # fmt: skip
    ypr = None if ypr_deg is None else _of_dtype(ypr_deg, dtype).contiguous()
    entry = torch.empty(B, dtype=torch.int64)
    image = torch.zeros(B, C, G, G, dtype=dtype)  # (the kernel's (B, C, G * G) and (B, G * G), in the shapes returned)
    mask = torch.zeros(B, 1, G, G, dtype=dtype)
    p = torch.empty(B, K, 2, dtype=dtype)
    support = torch.empty(B, K, dtype=dtype)
    flags = torch.empty(3, B, K, dtype=torch.bool)  # converged, valid, present
    out = torch.empty(3, B, dtype=dtype)  # dissimilarity, confidence, inside
    dmax = dc.max_displacement
    ptr = [x.data_ptr() for x in inputs]
    # the rows' addresses of the flags (bytes) and of out (``size`` bytes a value)
    f, o, size = flags.data_ptr(), out.data_ptr(), out.element_size()
    prob = _native.ConfProblem(
        B=B, V=mean.shape[0], F=faces.shape[0], M=face_index.shape[0], C=C, G=G, height=H, width=W, K=K, n=n,
        radius=kernel.numel() // 2 if sigma > 0 else 0, iterations=dc.iterations,
        project_out_bias=int(dc.project_out_bias), has_max_displacement=int(dmax is not None),
        min_patches=int(dc.min_patches), S=shape_units.shape[0], A=anim_units.shape[0], E=E, fx=cam.fx, fy=cam.fy,
        cx=cam.cx, cy=cam.cy, min_facing_cos=float(config.min_facing_cos), min_gain=0.05,
        depth_eps=torch.finfo(dtype).eps, eps=torch.finfo(dtype).eps, tolerance=float(dc.tolerance),
        max_displacement=float(dmax or 0.0), max_displacement_or_inf=float("inf") if dmax is None else float(dmax),
        min_support=float(dc.min_support), min_present_fraction=float(dc.min_present_fraction), d0=float(dc.d0),
        trim_fraction=float(dc.trim_fraction),
        mean=mean.data_ptr(), shape_units=shape_units.data_ptr(), anim_units=anim_units.data_ptr(),
        faces=faces.data_ptr(), surface=surface.data_ptr(), shape=ptr[0], alpha=ptr[1], R=ptr[2], t=ptr[3],
        ypr=None if ypr is None else ypr.data_ptr(), face_index=face_index.data_ptr(),
        pixel_index=pixel_index.data_ptr(), bary=bary.data_ptr(), frames=ptr[4], illumination=ptr[5], rows=ptr[6],
        mosaic_ypr=ptr[7], used=ptr[8], kernel=kernel.data_ptr(), patch_valid=ptr[9], grid=grid.data_ptr(),
        templ=template.data_ptr(), sd=sd.data_ptr(), ref_weight=ref_weight.data_ptr(),
        ref_total=ref_total.data_ptr(), out_entry=entry.data_ptr(), out_image=image.data_ptr(),
        out_mask=mask.data_ptr(), out_p=p.data_ptr(), out_support=support.data_ptr(), out_converged=f,
        out_valid=f + B * K, out_present=f + 2 * B * K, out_dissimilarity=o, out_confidence=o + B * size,
        out_inside=o + 2 * B * size,
    )  # fmt: skip
    _native.run("confidence", dtype == torch.float64, prob, B, torch.get_num_threads())
    diss, conf, inside = out.unbind(0)  # (at once: a row taken by indexing is an operation of its own)
    return diss, conf, inside, (image, mask), entry


@dataclass(frozen=True, eq=False)
class SearchResult:
    """The best placement :func:`search_mosaic` found for one stream.

    Attributes:
        rotation: ``(3, 3)`` the entry's rotation; translation: ``(3,)`` mm; entry: the entry index;
        score: its normalised cross-correlation in ``[-1, 1]`` (-1 when nothing could be placed).
    """

    rotation: Tensor
    translation: Tensor
    entry: int
    score: float


#: About the most bytes one of :func:`_ncc`'s ``(H, P, n)`` tensors takes at once (it splits its hypotheses).
_NCC_CHUNK_BYTES = 1 << 20


def _ncc(gray: Tensor, intrinsics: Intrinsics, X: Tensor, T: Tensor, w: Tensor, t: Tensor, min_inside: float) -> Tensor:
    """Zero-mean normalised cross-correlation of placed point sets with an image.

    Args:
        gray: ``(1, 1, h, w)``; X: ``(H, n, 3)`` rotated points (head origin at 0); T: ``(H, n)`` their
            intensities; w: ``(H, n)`` 1 for points taking part, else 0; t: ``(H, P, 3)`` placements.

    Returns:
        ``(H, P)`` in ``[-1, 1]``, -1 where fewer than ``min_inside`` of the points project inside the image
        (a point whose sample touches a NaN pixel, missing data, is not inside) or none does. Points whose intensity ``T`` is not
        finite take no part.
    """
    H, P = t.shape[:2]
    # A few hypotheses at a time, their (rows, P, n) tensors within about 1 MiB: the search's first stage over all of
    # them at once (2 MiB a tensor at 320x240 with the widened depths) ran 1.4 times as long on a 2-core CPU with
    # 1 MiB of L2 cache a core. The rows are independent: the same values as at once.
    rows = max(1, _NCC_CHUNK_BYTES // max(1, P * X.shape[1] * X.element_size()))
    if rows < H:
        return torch.cat([_ncc(gray, intrinsics, X[i : i + rows], T[i : i + rows], w[i : i + rows], t[i : i + rows],
                               min_inside) for i in range(0, H, rows)])  # fmt: skip
    u, v, ok, grid = _project_placed(X, t, intrinsics, gray.shape[-2], gray.shape[-1])
    # sample_at_pixels' bilinear sampling and inside test (the values of project_points and sample_at_pixels of the
    # placed points, to the bit; tests/template/test_management.py), on the coordinates one by one: their (.., 2)
    # and (.., 3) forms made the search's first stage about 1.6 times as slow (the copies and the reductions over
    # the last dimension of size 2 and 3 outweighed the arithmetic).
    vals = torch.nn.functional.grid_sample(gray, grid.to(gray.dtype), mode="bilinear", padding_mode="border",
                                           align_corners=True).reshape(H, P, -1)  # fmt: skip
    h, wd = gray.shape[-2:]
    inside = (u >= 0) & (u <= wd - 1) & (v >= 0) & (v <= h - 1) & ok
    return _sampled_ncc(vals, inside, T, w, min_inside)


def _sampled_ncc(vals: Tensor, inside: Tensor, T: Tensor, w: Tensor, min_inside: float) -> Tensor:
    """:func:`_ncc` of the samples: ``vals (H, P, n)`` the image at the placed points, ``inside (H, P, n)`` bool
    where they lie inside it, ``T (H, n)`` the points' intensities and ``w (H, n)`` their weights (a sample or an
    intensity that is not finite takes no part)."""
    usable = torch.isfinite(T)  # an entry built from a frame with infinite pixels (only first frames are checked)
    T, w = torch.where(usable, T, 0.0), w * usable.to(w.dtype)
    # A NaN (or infinite) sample would make its placement's score NaN, which topk ranks first and no comparison
    # then accepts: one NaN row in the frame left every search empty.
    finite = torch.isfinite(vals)
    if not bool(finite.all()):
        vals, inside = torch.where(finite, vals, 0.0), inside & finite
    wgt = inside.to(vals.dtype) * w.unsqueeze(1)
    cnt = wgt.sum(-1)
    mean_v = (vals * wgt).sum(-1, keepdim=True) / cnt.clamp_min(1).unsqueeze(-1)
    mean_t = (T.unsqueeze(1) * wgt).sum(-1, keepdim=True) / cnt.clamp_min(1).unsqueeze(-1)
    a = (vals - mean_v) * wgt
    b = (T.unsqueeze(1) - mean_t) * wgt
    ncc = (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1)).clamp_min(1e-6)
    # (a hypothesis without points, an entry with none at this level, is not placed: its 0 would outrank -1)
    placed = (cnt >= min_inside * w.sum(-1, keepdim=True)) & (cnt > 0)
    return torch.where(placed, ncc, torch.full_like(ncc, -1.0))


def _project_placed(
    X: Tensor, t: Tensor, intrinsics: Intrinsics, height: int, width: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The pixels of the points ``X (H, n, 3)`` placed at ``t (H, P, 3)``, as :func:`project_points` of ``X + t``
    then :func:`sample_at_pixels` on a ``height x width`` image make them: ``u, v (H, P, n)`` (0 where not finite),
    ``ok (H, P, n)`` (finite) and ``grid (1, 1, H P n, 2)``, grid_sample's coordinates (align_corners)."""
    H, P, n = t.shape[0], t.shape[1], X.shape[1]
    cam = check_intrinsics(intrinsics)
    dtype = torch.promote_types(X.dtype, t.dtype)
    grid = torch.empty(H, P, n, 2, dtype=dtype, device=X.device)
    x, y = grid.unbind(-1)  # filled with the camera-frame x and y first, then the grid's coordinates
    torch.add(X[..., 0].unsqueeze(1), t[..., 0].unsqueeze(2), out=x)
    torch.add(X[..., 1].unsqueeze(1), t[..., 1].unsqueeze(2), out=y)
    z = (X[..., 2].unsqueeze(1) + t[..., 2].unsqueeze(2)).clamp(min=torch.finfo(dtype).eps)  # project_points' depth
    u = cam.fx * x / z + cam.cx
    v = cam.fy * y / z + cam.cy
    ok = torch.isfinite(u) & torch.isfinite(v)
    if not bool(ok.all()):
        u, v = torch.where(ok, u, 0.0), torch.where(ok, v, 0.0)
    scale = u.new_tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)])  # pixels_to_grid
    torch.mul(u, scale[0], out=x)
    torch.mul(v, scale[1], out=y)
    return u, v, ok, grid.sub_(1.0).reshape(1, 1, -1, 2)


def _placements(grid: Tensor, depth: Tensor, intrinsics: Intrinsics) -> Tensor:
    """``(P, 2)`` pixels and ``(H,)`` depths -> ``(H, P, 3)`` translations putting the head origin there."""
    z = depth.reshape(-1, 1)
    return torch.stack(
        [(grid[:, 0] - intrinsics.cx) * z / intrinsics.fx, (grid[:, 1] - intrinsics.cy) * z / intrinsics.fy,
         z.expand(-1, grid.shape[0])], dim=-1,
    )  # fmt: skip


def search_mosaic(
    model: FaceModel,
    shape_coeffs: Tensor,
    mosaic: Mosaic,
    stream: int,
    gray: Tensor,
    intrinsics: Intrinsics,
    level: int,
    depth_mm: float,
    extra_rotation: Tensor | None,
    config: TemplateConfig,
    depth_scale: float = 1.0,
    backend: Backend = Backend.AUTO,
) -> SearchResult:
    """Find the face of ``stream`` in a gray image by placing its mosaic entries (module docstring).

    Hypotheses: every used entry at its own rotation (and, with ``extra_rotation``, the entry nearest that
    rotation placed at it: the last confident pose), each at the depths ``depth_mm * search_depth_factors``.
    Each is scored by the zero-mean normalised cross-correlation between its level-``level`` template
    intensities and the image sampled at their projections, over points facing the camera (placements with
    fewer than ``search_min_inside`` of them inside the image score -1). Two stages: the head origin on a grid
    of step ``search_step_px`` on the image halved once more (``2 * search_step_px`` pixels of ``gray``; a
    quarter of ``search_points`` points),
    then, around the four best placements, a grid of step 1 pixel on ``gray`` itself with ``search_points``
    points.

    Args:
        shape_coeffs: ``(1, S)`` the stream's shape units.
        stream: the stream's index in ``mosaic``.
        gray: ``(1, 1, h, w)`` the frame at pyramid level ``level``, gray in [0, 1], ``h, w >= 2``; intrinsics: its
            camera.
        depth_mm: the last confident depth of the head origin.
        extra_rotation: ``(3, 3)`` or None.
        depth_scale: other than 1, the depths ``depth_mm * depth_scale * search_depth_factors`` are tried too
            (:meth:`TemplateConfig.depth_scale`).
        backend: :class:`~torchface.backend.Backend` of the entries' template points (the tracker's).

    Returns:
        :class:`SearchResult` (score -1 when nothing could be placed).
    """
    if gray.dim() != 4 or gray.shape[:2] != (1, 1) or min(gray.shape[-2:]) < 2:
        raise ValueError(f"gray must be (1, 1, h, w) with h, w >= 2 (the search halves it), got {tuple(gray.shape)}")
    dtype, device = gray.dtype, gray.device
    lv = mosaic.levels[level]
    used = mosaic.used[stream].nonzero().squeeze(-1)
    rots = mosaic.rotation[stream, used]  # (E', 3, 3)
    ent = used.clone()
    if extra_rotation is not None:
        ypr = matrix_to_euler(extra_rotation.unsqueeze(0))
        d = (mosaic.ypr_deg[stream, used][:, :2] - ypr[:, :2]).norm(dim=-1)
        ent = torch.cat([ent, used[d.argmin()].reshape(1)])
        rots = torch.cat([rots, extra_rotation.unsqueeze(0).to(rots.dtype)])
    n_rot = rots.shape[0]
    tpl = template_at(
        model, shape_coeffs.expand(n_rot, -1), lv.face_index[stream, ent], lv.bary[stream, ent],
        lv.intensity[stream, ent], lv.valid[stream, ent], backend=backend,
    )  # fmt: skip
    # Points facing the camera at the hypothesis' rotation (viewing ray ~ +z for a face near the axis); the
    # first n of them, a uniform subset (template slots are in random order), packed to the front.
    normals_cam = torch.matmul(tpl.normals, rots.transpose(1, 2))
    keep = tpl.valid & (normals_cam[..., 2] < -0.2)
    order = torch.argsort((~keep).to(torch.int8), dim=-1, stable=True)[:, : config.search_points]
    w = torch.gather(keep, 1, order).to(dtype)  # (R, n)
    X = torch.matmul(torch.gather(tpl.points, 1, order.unsqueeze(-1).expand(-1, -1, 3)), rots.transpose(1, 2))
    T = torch.gather(tpl.intensity, 1, order)
    # Hypotheses: rotations x depths.
    factor_values = config.search_depth_factors
    n_base = len(factor_values)
    if depth_scale != 1.0:
        factor_values = (*factor_values, *(depth_scale * f for f in factor_values))
    factors = torch.tensor(factor_values, dtype=dtype, device=device)
    n_d = factors.shape[0]
    depth = (depth_mm * factors).repeat(n_rot)  # (H,)
    # A widened depth must out-score the base depths by a margin to be chosen (ranking only; the score reported
    # is the correlation itself): a wrong placement at another depth can correlate about as well as the face.
    handicap = (torch.arange(n_d, device=device) >= n_base).to(dtype).repeat(n_rot) * _WIDENED_DEPTH_MARGIN
    Xh, Th, wh = (x.repeat_interleave(n_d, dim=0) for x in (X, T, w))
    hyp_rot = torch.arange(n_rot, device=device).repeat_interleave(n_d)
    # Stage 1: coarse grid on the image halved once more, a quarter of the points.
    half = torch.nn.functional.avg_pool2d(gray, 2)
    cam_half = Intrinsics(half.shape[-1], half.shape[-2], intrinsics.fx / 2, intrinsics.fy / 2,
                          (intrinsics.cx + 0.5) / 2 - 0.5, (intrinsics.cy + 0.5) / 2 - 0.5)  # fmt: skip
    step = config.search_step_px
    vv, uu = torch.meshgrid(torch.arange(0.0, half.shape[-2], step, dtype=dtype, device=device),
                            torch.arange(0.0, half.shape[-1], step, dtype=dtype, device=device), indexing="ij")
    grid = torch.stack([uu.reshape(-1), vv.reshape(-1)], -1)
    n1 = max(8, config.search_points // 4)
    ncc1 = _ncc(half, cam_half, Xh[:, :n1], Th[:, :n1], wh[:, :n1], _placements(grid, depth, cam_half),
                config.search_min_inside)  # fmt: skip
    top = torch.topk((ncc1 - handicap.unsqueeze(-1)).reshape(-1), min(4, ncc1.numel())).indices
    best = SearchResult(torch.eye(3, dtype=dtype, device=device), torch.zeros(3, dtype=dtype, device=device), 0, -1.0)
    best_rank = -math.inf
    # Stage 2: around each of the best, step 1 pixel on ``gray``, all the points.
    r = int(round(step)) + 1
    offsets = torch.arange(-r, r + 1, dtype=dtype, device=device)
    ov, ou = torch.meshgrid(offsets, offsets, indexing="ij")
    local = torch.stack([ou.reshape(-1), ov.reshape(-1)], -1)  # (Q, 2)
    # The best placed ones (not -1), scored in one _ncc call (a row each, as one call each) and taken in turn.
    hp = [divmod(flat, grid.shape[0]) for flat in top.tolist()]
    hp = [(h, p) for h, p in hp if not float(ncc1[h, p]) <= -1.0]
    if hp:
        hs = torch.tensor([h for h, _ in hp], dtype=torch.int64, device=device)
        # around the half image's pixel centre, in ``gray`` pixels
        t = torch.cat([_placements((grid[p] + 0.5) * 2 - 0.5 + local, depth[h : h + 1], intrinsics) for h, p in hp])
        ncc2 = _ncc(gray, intrinsics, Xh[hs], Th[hs], wh[hs], t, config.search_min_inside)  # (len(hp), Q)
        scores, qs = ncc2.max(1)
        for i, (h, _) in enumerate(hp):
            score, q = float(scores[i]), int(qs[i])
            rank = score - float(handicap[h])
            if rank > best_rank:
                k = int(hyp_rot[h])
                best, best_rank = SearchResult(rots[k], t[i, q], int(ent[k]), score), rank
    return best


def params_from_pose(rotation: Tensor, translation: Tensor, anim: Tensor, light: Tensor) -> Tensor:
    """Pack ``(B, 3, 3)``, ``(B, 3)``, ``(B, A)``, ``(B, L)`` into ``(B, 3 + 3 + A + L)`` parameters
    (:class:`torchface.tracker.params.ParamLayout` order: axis-angle, translation, animation, illumination)."""
    return torch.cat([matrix_to_axis_angle(rotation), translation, anim, light], dim=-1)

