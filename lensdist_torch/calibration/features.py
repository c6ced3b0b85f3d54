"""A sequence's features and verified matches in a COLMAP database, the same on every run.

COLMAP's SIFT on every frame (at most ``max_image_side`` px and :func:`feature_cap` features) in
fixed shards of the frames (:func:`extract_in_shards`), exhaustive matching (or sequential for a
video's many frames), and the geometric verification in fixed shards of the pairs
(:func:`verify_in_shards`). :func:`~lensdist_torch.calibration.multiview.reconstruct`
maps on the database; :func:`~lensdist_torch.calibration.matches.read_verified_matches` reads it.

References:
    J. L. Schönberger, J.-M. Frahm, "Structure-from-Motion Revisited", CVPR 2016 (COLMAP: features,
    matching, geometric verification).
"""

from __future__ import annotations

import copy
import math
import shutil
import tempfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from lensdist_torch.calibration.multiview_fits import pycolmap_or_error, quiet_log
from lensdist_torch.config import MultiViewConfig
from lensdist_torch.config.checks import or_defaults

__all__ = ["EXHAUSTIVE_BELOW", "FEATURES_PER_MEGAPIXEL", "SEQUENTIAL_OVERLAP", "feature_cap", "extraction_options",
           "extract_and_match", "extract_in_shards", "verify_in_shards"]

#: Up to this many frames every pair is matched; more (a video's): sequential matching, as the frames' order is
#: the recording's.
EXHAUSTIVE_BELOW = 30
#: Sequential matching's ``overlap``: COLMAP's quadratic overlap matches each frame with the frames 1, 2, 4, ...,
#: 2^(overlap - 1) after it (a video's frames beyond :data:`EXHAUSTIVE_BELOW`).
SEQUENTIAL_OVERLAP = 12
#: SIFT features per megapixel of the frame as SIFT reads it, at most (and ``max_features``); matching and mapping
#: scale with the features.
FEATURES_PER_MEGAPIXEL = 8192.0

def feature_cap(config: MultiViewConfig, image_size: tuple[int, int] | None = None) -> int:
    """SIFT features per frame at most (``max_features``, and by area where the frames' size is known).

    :data:`FEATURES_PER_MEGAPIXEL` of the frame's area as SIFT reads it (at most ``max_image_side``
    long) where ``image_size`` (H, W) is given; never below 64.

    Example:
        >>> feature_cap(MultiViewConfig(), (288, 384)), feature_cap(MultiViewConfig(), (1080, 1920))
        (906, 8192)
    """
    if image_size is None:
        return config.max_features
    h, w = image_size
    shrink = min(1.0, config.max_image_side / max(h, w))
    return max(64, min(config.max_features, math.ceil(FEATURES_PER_MEGAPIXEL * h * w * shrink * shrink / 1e6)))


def extraction_options(config: MultiViewConfig, image_size: tuple[int, int] | None = None):
    """COLMAP's reader and SIFT options as :func:`extract_and_match` sets them: ``(reader, extraction)``.

    One shared RADIAL camera; frames read at most ``max_image_side`` long, at most
    :func:`feature_cap` features each, on the CPU.
    """
    pc = pycolmap_or_error()
    reader = pc.ImageReaderOptions()
    reader.camera_model = "RADIAL"
    extraction = pc.FeatureExtractionOptions()
    extraction.max_image_size, extraction.use_gpu = config.max_image_side, False
    extraction.sift.max_num_features = feature_cap(config, image_size)
    return reader, extraction


def extract_and_match(
    database: str | Path,
    image_dir: str | Path,
    names: list[str],
    *,
    config: MultiViewConfig | None = None,
    image_size: tuple[int, int] | None = None,
    on_stage: Callable[[str, int], None] | None = None,
) -> None:
    """COLMAP's SIFT features of frames ``names`` and their verified matches, into a new ``database`` (step 1).

    Exhaustive matching up to :data:`EXHAUSTIVE_BELOW` frames, sequential beyond; one shared RADIAL
    camera; the geometric verification's RANSAC seeded by ``seed``. ``on_stage`` is called as
    each stage starts with its name ("extraction", "matching", "verification") and the threads it
    runs on.
    :func:`~lensdist_torch.calibration.multiview.reconstruct` maps on it;
    :func:`~lensdist_torch.calibration.matches.read_verified_matches` reads its matches.

    A run repeats bit for bit whatever ``num_threads``: the extraction runs in ``num_threads`` fixed
    shards of consecutive frames, one thread each (:func:`extract_in_shards`; with COLMAP's own
    threads, frames entered the database in the order their threads finished), the matching on
    one thread (on two, COLMAP's CPU matcher now and then kept a fraction of a pair's matches:
    docs/method.md, section 11) and the verification in ``num_threads`` fixed shards of the
    matched pairs, one thread each (:func:`verify_in_shards`; COLMAP's own threads each draw from a
    seeded generator whichever pairs they are handed, so the verified matches, and every answer
    after them, changed from run to run).
    """
    pc, cfg = pycolmap_or_error(), or_defaults(config, MultiViewConfig)
    pc.set_random_seed(cfg.seed)
    reader, extraction = extraction_options(cfg, image_size)
    matching = pc.FeatureMatchingOptions()
    matching.num_threads, matching.use_gpu, matching.skip_geometric_verification = 1, False, True
    verification = pc.TwoViewGeometryOptions()
    verification.ransac.random_seed = cfg.seed  # COLMAP's default (-1) seeds every RANSAC from the clock
    stage = on_stage or (lambda name, threads: None)
    with quiet_log():
        stage("extraction", cfg.num_threads)
        extract_in_shards(database, image_dir, names, reader=reader, extraction=extraction, threads=cfg.num_threads)
        stage("matching", matching.num_threads)
        if len(names) <= EXHAUSTIVE_BELOW:
            pc.match_exhaustive(
                database, matching_options=matching, verification_options=verification, device=pc.Device.cpu
            )
        else:
            pairing = pc.SequentialPairingOptions()
            pairing.overlap = SEQUENTIAL_OVERLAP
            pc.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                verification_options=verification, device=pc.Device.cpu)
        stage("verification", cfg.num_threads)
        verify_in_shards(database, verification, threads=cfg.num_threads)


def extract_in_shards(database: str | Path, image_dir: str | Path, names: list[str], *, reader, extraction,
                      threads: int) -> None:
    """COLMAP's features of frames ``names`` into a new ``database`` in ``threads`` fixed shards, as one thread.

    The frames are dealt into ``threads`` shards of consecutive frames; each shard is extracted
    on one thread into a database of its own, the shards side by side, and their frames are
    written into ``database`` in the order of ``names``: one shared camera (the first frame's,
    as COLMAP's single-camera mode makes it), each frame's rig frame, image, keypoints and
    descriptors under the ids one thread gives them (1, 2, ... in that order), bit for bit.

    Args:
        database: the database to create (it must not hold frames yet).
        image_dir: the folder of the frames.
        names: the frames' file names in it, in recording order.
        reader: ``pycolmap.ImageReaderOptions`` (its camera model).
        extraction: ``pycolmap.FeatureExtractionOptions``; each shard runs it on one thread.
        threads: the shards, at least 1 (at most one a frame). The shards' databases live in a
            temporary folder beside ``database`` and go with it, whatever happens.
    """
    if not (isinstance(threads, int) and threads >= 1):
        raise ValueError(f"threads must be a positive int, got {threads!r}")
    pc = pycolmap_or_error()
    database, names = Path(database), list(names)
    n = max(1, min(threads, len(names)))
    bounds = [round(k * len(names) / n) for k in range(n + 1)]
    extraction = copy.copy(extraction)
    extraction.num_threads = 1

    def extract(k: int, path: Path) -> None:
        pc.extract_features(path, image_dir, image_names=names[bounds[k]: bounds[k + 1]],
                            camera_mode=pc.CameraMode.SINGLE, reader_options=reader,
                            extraction_options=extraction, device=pc.Device.cpu)

    with tempfile.TemporaryDirectory(prefix="lensdist-extract-", dir=database.parent) as tmp:
        shards = [Path(tmp) / f"shard{k}.db" for k in range(n)]
        with ThreadPoolExecutor(n) as pool:  # COLMAP lets Python's lock go while it extracts
            list(pool.map(extract, range(n), shards))
        first = pc.Database.open(shards[0])
        try:
            (camera,), (rig,) = first.read_all_cameras(), first.read_all_rigs()
        finally:
            first.close()
        db = pc.Database.open(database)
        try:
            db.write_camera(camera, use_camera_id=True)
            db.write_rig(rig, use_rig_id=True)
            image_id = 0
            for path in shards:
                part = pc.Database.open(path)
                try:
                    for image in sorted(part.read_all_images(), key=lambda im: im.image_id):
                        image_id += 1  # frame and image share the id, as one thread numbers them
                        frame = pc.Frame()
                        frame.frame_id, frame.rig_id = image_id, rig.rig_id
                        frame.add_data_id(pc.data_t(camera.sensor_id, image_id))
                        db.write_frame(frame, use_frame_id=True)
                        new = pc.Image(name=image.name, camera_id=camera.camera_id, image_id=image_id)
                        new.frame_id = image_id
                        db.write_image(new, use_image_id=True)
                        db.write_keypoints(image_id, part.read_keypoints(image.image_id))
                        db.write_descriptors(image_id, part.read_descriptors(image.image_id))
                finally:
                    part.close()
        finally:
            db.close()


def verify_in_shards(database: str | Path, verification, *, threads: int) -> None:
    """COLMAP's geometric verification of every matched pair in ``database``, in ``threads`` fixed shards.

    The pairs (by pair id) are dealt into ``threads`` shards; each is verified on one thread in a
    copy of the database holding only its matches, the shards side by side, and their two-view
    geometries are written into ``database``. The same pairs meet the same seeded RANSAC in the
    same order on every run.

    Args:
        database: a COLMAP database with features and (unverified) matches.
        verification: ``pycolmap.TwoViewGeometryOptions`` (its RANSAC seeded).
        threads: the shards, at least 1 (at most one a pair). The copies live in a temporary
            folder beside ``database`` and go with it, whatever happens.
    """
    if not (isinstance(threads, int) and threads >= 1):
        raise ValueError(f"threads must be a positive int, got {threads!r}")
    pc = pycolmap_or_error()
    database = Path(database)
    db = pc.Database.open(database)
    try:
        pairs = sorted(db.read_num_matches()[0])  # the pairs' ids, not their matches
    finally:
        db.close()
    n = max(1, min(threads, len(pairs)))

    def verify(k: int, path: Path) -> None:  # one shard: a copy holding only its pairs' matches
        shutil.copyfile(database, path)
        part = pc.Database.open(path)
        try:
            for i, pair in enumerate(pairs):
                if i % n != k:
                    part.delete_matches(*pc.pair_id_to_image_pair(pair))
        finally:
            part.close()
        options = pc.GeometricVerifierOptions()
        options.num_threads = 1
        pc.geometric_verification(path, verifier_options=options, two_view_geometry_options=verification)

    with tempfile.TemporaryDirectory(prefix="lensdist-verify-", dir=database.parent) as tmp:
        shards = [Path(tmp) / f"shard{k}.db" for k in range(n)]
        with ThreadPoolExecutor(n) as pool:  # COLMAP lets Python's lock go while it verifies
            list(pool.map(verify, range(n), shards))
        db = pc.Database.open(database)
        try:
            for path in shards:
                part = pc.Database.open(path)
                try:
                    for pair, geometry in zip(*part.read_two_view_geometries()):
                        db.write_two_view_geometry(*pc.pair_id_to_image_pair(pair), geometry)
                finally:
                    part.close()
        finally:
            db.close()
