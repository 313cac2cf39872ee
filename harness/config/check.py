"""Range checks of a loaded config that a dataclass cannot express (all at load time).

Each failure is one :class:`~harness.errors.ConfigError` naming the key, the value and what is
allowed.
"""

from __future__ import annotations

import itertools
import math
import re
from pathlib import Path
from typing import Any

from harness.config.schema import (
    ALIGNERS,
    FEATURE_IMAGES,
    KEYPOINTS,
    PAIR_MODES,
    PRECISIONS,
    BovwConfig,
    Config,
    DescriptorConfig,
    LocalConfig,
)
from harness.errors import ConfigError
from harness.methods import (
    BOX_GENERATORS,
    BOX_PRIORS,
    BOX_SCORES,
    DETECT_LOCALIZERS,
    known_fusion_methods,
    known_proposal_methods,
)


def check_bovw(bw: BovwConfig, where: str) -> None:
    """Ranges of a ``bovw`` table."""
    c = check_value
    c(bw.features in ("sift", "rootsift", "orb"), where, "features", bw.features,
      "'sift', 'rootsift' or 'orb'")  # fmt: skip
    c(2 <= bw.k <= 1_000_000, where, "k", bw.k, "[2, 1e6]")
    c(bw.step >= 1, where, "step", bw.step, ">= 1")
    c(bw.patch >= 4, where, "patch", bw.patch, ">= 4")
    c(bw.input_size >= 16, where, "input_size", bw.input_size, ">= 16")
    c(bw.max_train_subimages >= 1, where, "max_train_subimages", bw.max_train_subimages, ">= 1")
    c(bw.max_train_features >= bw.k, where, "max_train_features", bw.max_train_features,
      f">= k ({bw.k})")  # fmt: skip
    c(bw.kmeans_iter >= 1, where, "kmeans_iter", bw.kmeans_iter, ">= 1")
    c(bw.seed >= 0, where, "seed", bw.seed, ">= 0")
    c(bw.shard_frames >= 1, where, "shard_frames", bw.shard_frames, ">= 1")
    c(bw.prefetch >= 0, where, "prefetch", bw.prefetch, ">= 0")


#: A session name is a directory name under ``--out``: letters, digits, ``.``, ``_``, ``-``, not
#: starting with a dot (so never ``..``, never a path).
SESSION_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def check_session_name(name: object, where: str) -> str:
    """A session (or camera) name that is safe as one directory or file name under ``--out``.

    Raises:
        ConfigError: The name is not a string, or holds a path separator, starts with a dot or
            another character outside letters, digits, ``.``, ``_`` and ``-``.
    """
    if not isinstance(name, str) or not SESSION_NAME.match(name):
        raise ConfigError(
            f"{where} = {name!r}: it names a directory or file the harness writes under --out, "
            "so it must be letters, digits, '.', '_' or '-', not start with '.' or '-', and "
            "hold no '/'"
        )
    return name


def check_value(ok: bool, where: str, key: str, value: Any, allowed: str) -> None:
    """Unless ``ok``, one ConfigError naming ``where``, ``key``, its value and what is allowed."""
    if not ok:
        raise ConfigError(f"{where}: {key} = {value!r} is out of range; allowed: {allowed}")


def _range(
    where: str, key: str, pair: tuple[float, float], lo: float = 0.0, hi: float = 1.0
) -> None:
    check_value(
        lo <= pair[0] <= pair[1] <= hi,
        where,
        key,
        list(pair),
        f"[low, high] with {lo} <= low <= high <= {hi}",
    )


#: The largest seed accepted anywhere (numpy's and torch's generators take 64-bit seeds).
MAX_SEED = 2**63 - 1


def _finite(v: Any) -> bool:
    return isinstance(v, int | float) and math.isfinite(v)


def check_ingest(ig: Any, where: str, flags: dict[str, str] | None = None) -> None:
    """The ingest options' ranges, for ``[ingest]`` and for ``harness ingest``'s flags alike.

    ``flags`` names each field's command-line flag, so that a flag's error names the flag.
    """
    name = {
        k: (flags or {}).get(k, f"[ingest] {k}")
        for k in ("max_pose_gap_s", "max_tf_gap_s", "max_image_pixels")
    }
    for key in ("max_pose_gap_s", "max_tf_gap_s"):
        v = getattr(ig, key)
        check_value(_finite(v) and v > 0, where, name[key], v, "> 0 seconds, finite")
    check_value(
        ig.max_image_pixels >= 1,
        where,
        name["max_image_pixels"],
        ig.max_image_pixels,
        ">= 1",
    )


def check_fixture(fx: Any, where: str, flags: dict[str, str] | None = None) -> None:
    """The fixture world's ranges, for ``[fixture]`` and for ``harness fixture``'s flags alike."""

    def name(k: str) -> str:
        return (flags or {}).get(k, f"[fixture] {k}")

    check_value(0 <= fx.seed <= MAX_SEED, where, name("seed"), fx.seed, f"0 .. {MAX_SEED}")
    check_value(fx.render_scale >= 1, where, name("render_scale"), fx.render_scale, ">= 1")
    check_value(fx.frames >= 1, where, name("frames"), fx.frames, ">= 1")
    for k in ("width", "height"):
        check_value(getattr(fx, k) >= 8, where, name(k), getattr(fx, k), ">= 8 pixels")
    check_value(fx.objects >= 0, where, name("objects"), fx.objects, ">= 0")
    check_value(
        _finite(fx.loop_scale) and fx.loop_scale > 0,
        where,
        name("loop_scale"),
        fx.loop_scale,
        "> 0, finite",
    )


def validate(cfg: Config, where: str) -> None:
    """Range checks that a dataclass cannot express, all at load time, before any work.

    One function per section, in the order they always ran.

    Raises:
        ConfigError: naming the key, the value and the allowed range.
    """
    _check_fusion(cfg, where)
    _check_pairs(cfg, where)
    mk = cfg.masks.min_mask_area
    check_value(mk >= 1, where, "[masks] min_mask_area", mk, ">= 1 pixel")
    _check_ingest_keys(cfg, where)
    _check_retrieval(cfg, where)
    _check_seeds(cfg, where)
    _check_projection(cfg, where)
    _check_descriptor(cfg, where)
    _check_proposals(cfg, where)
    _check_splits(cfg, where)
    _check_report(cfg, where)
    _check_detect(cfg, where)
    _check_fixture_keys(cfg, where)
    _device(cfg.descriptor.device, where, "[descriptor] device")


def _check_fusion(cfg: Config, where: str) -> None:
    """The import score kind and ``[fusion]``: known methods, each once, their options."""
    c = check_value
    fu = cfg.fusion
    fusion_methods = known_fusion_methods  # SPEC section 7's and registered ones

    c(
        cfg.import_.score_kind in ("distance", "similarity"),
        where,
        "[import] score_kind",
        cfg.import_.score_kind,
        "'distance' or 'similarity'",
    )
    bad = [m for m in fu.methods if m not in fusion_methods()]
    c(
        not bad and len(fu.methods) > 0,
        where,
        "[fusion] methods",
        list(fu.methods),
        f"a non-empty list of {list(fusion_methods())}",
    )
    c(
        len(set(fu.methods)) == len(fu.methods),
        where,
        "[fusion] methods",
        list(fu.methods),
        "each method once",
    )
    c(fu.max_fused_boxes >= 1, where, "[fusion] max_fused_boxes", fu.max_fused_boxes, ">= 1")
    c(fu.rrf_c >= 0, where, "[fusion] rrf_c", fu.rrf_c, "a number >= 0")


def _check_pairs(cfg: Config, where: str) -> None:
    """``[pairs]``: the heading gate, distances, which queries."""
    c = check_value
    pa = cfg.pairs
    c(
        0 < pa.max_yaw_diff_deg <= 180,
        where,
        "[pairs] max_yaw_diff_deg",
        pa.max_yaw_diff_deg,
        "(0, 180]",
    )
    c(
        pa.max_distance_m is None or pa.max_distance_m > 0,
        where,
        "[pairs] max_distance_m",
        pa.max_distance_m,
        "> 0 metres",
    )
    c(pa.stride_m >= 0, where, "[pairs] stride_m", pa.stride_m, ">= 0 metres")
    c(
        pa.queries in ("annotated", "all"),
        where,
        "[pairs] queries",
        pa.queries,
        "'annotated' or 'all'",
    )
    c(
        pa.by in PAIR_MODES,
        where,
        "[pairs] by",
        pa.by,
        " or ".join(repr(m) for m in PAIR_MODES),
    )
    c(pa.place_frames >= 0, where, "[pairs] place_frames", pa.place_frames, ">= 0 frames")
    c(pa.sequence_frames >= 1, where, "[pairs] sequence_frames", pa.sequence_frames, ">= 1")
    c(
        0 <= pa.min_pair_confidence <= 1,
        where,
        "[pairs] min_pair_confidence",
        pa.min_pair_confidence,
        "in [0, 1]",
    )
    if pa.by != "pose":
        rc, rp = cfg.retrieval, cfg.report
        c(
            rc.db_stride_m == 0,
            where,
            "[retrieval] db_stride_m",
            rc.db_stride_m,
            f"0 with [pairs] by = {pa.by!r} (a database thinned by distance needs poses)",
        )
        c(
            rp.gt_radius_also == 0,
            where,
            "[report] gt_radius_also",
            rp.gt_radius_also,
            f"0 with [pairs] by = {pa.by!r} (a place radius needs poses)",
        )


def _check_ingest_keys(cfg: Config, where: str) -> None:
    """``[ingest]``: the gaps and limits (:func:`check_ingest`), time source, storage, rotation."""
    c = check_value
    ig = cfg.ingest
    check_ingest(ig, where)
    c(
        ig.time_source in ("header", "log"),
        where,
        "[ingest] time_source",
        ig.time_source,
        "'header' or 'log'",
    )
    c(
        ig.store_format in ("tiff", "png"),
        where,
        "[ingest] store_format",
        ig.store_format,
        "'tiff' or 'png'",
    )
    c(
        ig.nclt_rotation in ("cw", "ccw", "none"),
        where,
        "[ingest] nclt_rotation",
        ig.nclt_rotation,
        "cw, ccw or none",
    )


def _check_retrieval(cfg: Config, where: str) -> None:
    """``[retrieval]``: the engine, the place radius against the database stride, sizes."""
    c = check_value
    re_ = cfg.retrieval
    c(
        re_.engine in ("exact", "faiss"),
        where,
        "[retrieval] engine",
        re_.engine,
        "'exact' or 'faiss'",
    )
    c(
        re_.db_stride_m >= 0,
        where,
        "[retrieval] db_stride_m",
        re_.db_stride_m,
        ">= 0 metres (0: every reference frame)",
    )
    c(
        re_.gt_radius_m >= 0,
        where,
        "[retrieval] gt_radius_m",
        re_.gt_radius_m,
        ">= 0 metres (0: the ground-truth frame alone)",
    )
    for key in ("chunk_rows", "query_batch", "faiss_nprobe", "query_frames_per_shard"):
        c(getattr(re_, key) >= 1, where, f"[retrieval] {key}", getattr(re_, key), ">= 1")
    c(re_.memory_mb > 0, where, "[retrieval] memory_mb", re_.memory_mb, "> 0 MiB")
    for key in ("faiss_nlist", "faiss_check"):
        c(getattr(re_, key) >= 0, where, f"[retrieval] {key}", getattr(re_, key), ">= 0")
    c(
        re_.db_stride_m == 0 or re_.gt_radius_m >= re_.db_stride_m / 2,
        where,
        "[retrieval] gt_radius_m",
        re_.gt_radius_m,
        f"at least half of db_stride_m = {re_.db_stride_m:g} (a place must keep a frame of the "
        "thinned database)",
    )


def _check_seeds(cfg: Config, where: str) -> None:
    """Every seed, the run's, each section's and each localizer's, in ``0 .. MAX_SEED``."""
    c = check_value
    c(0 <= cfg.seed <= MAX_SEED, where, "seed", cfg.seed, f"0 .. {MAX_SEED}")
    for section in ("descriptor", "projection", "fusion", "proposals", "retrieval"):
        sub = getattr(cfg, section, None)
        if sub is not None and hasattr(sub, "seed"):
            c(0 <= sub.seed <= MAX_SEED, where, f"[{section}] seed", sub.seed, f"0 .. {MAX_SEED}")
    for lc in cfg.localizers:
        if lc.descriptor is not None:
            c(
                0 <= lc.descriptor.seed <= MAX_SEED,
                where,
                f"[[localizers]] {lc.name}: [descriptor] seed",
                lc.descriptor.seed,
                f"0 .. {MAX_SEED}",
            )


def _check_projection(cfg: Config, where: str) -> None:
    """``[projection]``: its dimension and the samples it is fitted on."""
    c = check_value
    pj = cfg.projection
    c(pj.dim >= 0, where, "[projection] dim", pj.dim, ">= 0 (0: the full descriptor)")
    c(
        pj.fit_samples >= max(pj.dim, 1),
        where,
        "[projection] fit_samples",
        pj.fit_samples,
        f">= dim ({pj.dim}) and >= 1",
    )


def _check_descriptor(cfg: Config, where: str) -> None:
    """``[descriptor]``: sizes, options, a user's network file."""
    c = check_value
    de = cfg.descriptor
    choices = (
        ("input_norm", ("none", "per_crop"), "'none' or 'per_crop'"),
        ("dtype", ("float16", "float32"), "float16 or float32"),
        ("precision", PRECISIONS, "'auto', 'fp32' or 'bf16'"),
        ("pooling", ("avg", "max", "gem"), "avg, max, gem"),
        ("decode", ("reduced", "full"), "reduced or full"),
    )
    for key, allowed, words in choices:
        c(getattr(de, key) in allowed, where, f"[descriptor] {key}", getattr(de, key), words)
    c(
        de.device in ("auto", "cpu", "cuda") or de.device.startswith("cuda:"),
        where,
        "[descriptor] device",
        de.device,
        "auto, cpu, cuda or cuda:N",
    )
    c(
        de.train_samples >= 0,
        where,
        "[descriptor] train_samples",
        de.train_samples,
        ">= 0 (0: train for epochs)",
    )
    c(0 <= de.holdout < 1, where, "[descriptor] holdout", de.holdout, "[0, 1)")
    c(
        de.eval_every >= 1 and de.patience >= 1,
        where,
        "[descriptor] eval_every, patience",
        (de.eval_every, de.patience),
        ">= 1 each",
    )
    c(
        de.encode_batch >= 0,
        where,
        "[descriptor] encode_batch",
        de.encode_batch,
        ">= 0 (0: automatic)",
    )
    for key in ("epochs", "batch_size", "max_train_subimages", "shard_frames"):
        c(getattr(de, key) >= 1, where, f"[descriptor] {key}", getattr(de, key), ">= 1")
    c(de.num_workers >= 0, where, "[descriptor] num_workers", de.num_workers, ">= 0")
    c(de.prefetch >= 0, where, "[descriptor] prefetch", de.prefetch, ">= 0")
    c(
        de.input_size >= 8 and de.input_size % 8 == 0,
        where,
        "[descriptor] input_size",
        de.input_size,
        "a multiple of 8, >= 8 pixels",
    )
    c(de.lr > 0, where, "[descriptor] lr", de.lr, "> 0")
    c(de.gem_p > 0, where, "[descriptor] gem_p", de.gem_p, "> 0")
    c(all(v > 0 for v in de.std), where, "[descriptor] std", list(de.std), "three values > 0")
    _check_network_file(de, where)
    c(
        all(ch >= 1 for ch in de.channels),
        where,
        "[descriptor] channels",
        list(de.channels),
        "three integers >= 1",
    )


def _check_network_file(de: DescriptorConfig, where: str) -> None:
    """A user's network (``torchscript``, ``onnx``) is a local file: nothing is downloaded."""
    if de.name in ("torchscript", "onnx"):
        check_value(bool(de.path), where, "[descriptor] path", de.path, f"the local {de.name} file")
        check_value(
            Path(de.path).is_file(),
            where,
            "[descriptor] path",
            de.path,
            "an existing file (nothing is downloaded at run time)",
        )


def _check_proposals(cfg: Config, where: str) -> None:
    """``[proposals]``: known methods, the files they need, each method's options."""
    c = check_value
    pr = cfg.proposals
    known_methods = known_proposal_methods  # the registry (built-ins and registered methods)

    badp = [m for m in pr.methods if m not in known_methods()]
    c(
        not badp and len(pr.methods) > 0,
        where,
        "[proposals] methods",
        list(pr.methods),
        f"a non-empty list of {list(known_methods())}",
    )
    c(
        "file" not in pr.methods or bool(pr.file),
        where,
        "[proposals] file",
        pr.file,
        "a path to a box table (the method 'file' is listed)",
    )
    c(
        "yolo" not in pr.methods or bool(pr.yolo.weights),
        where,
        "[proposals.yolo] weights",
        pr.yolo.weights,
        "a local weights path (the method 'yolo' is listed)",
    )
    c(0 <= pr.yolo.conf <= 1, where, "[proposals.yolo] conf", pr.yolo.conf, "[0, 1]")
    c(0 < pr.yolo.iou <= 1, where, "[proposals.yolo] iou", pr.yolo.iou, "(0, 1]")
    for key in ("imgsz", "batch", "max_det"):
        c(
            getattr(pr.yolo, key) >= 1,
            where,
            f"[proposals.yolo] {key}",
            getattr(pr.yolo, key),
            ">= 1",
        )
    c(
        pr.yolo.imgsz % 32 == 0,
        where,
        "[proposals.yolo] imgsz",
        pr.yolo.imgsz,
        "a multiple of 32 (YOLO strides)",
    )
    _device(pr.yolo.device, where, "[proposals.yolo] device")
    c(
        all(d >= 1 and d % 2 == 1 for d in pr.edges.dilations) and len(pr.edges.dilations) > 0,
        where,
        "[proposals.edges] dilations",
        list(pr.edges.dilations),
        "a non-empty list of odd kernel sizes >= 1",
    )
    seg = pr.segments
    c(2 <= seg.k <= 64, where, "[proposals.segments] k", seg.k, "a colour cluster count in [2, 64]")
    c(
        all(d >= 1 for d in seg.closings) and len(seg.closings) > 0,
        where,
        "[proposals.segments] closings",
        list(seg.closings),
        "a non-empty list of kernel sizes >= 1",
    )
    for sub_name in ("edges", "mser", "segments"):
        sub = getattr(pr, sub_name)
        c(sub.max_boxes >= 1, where, f"[proposals.{sub_name}] max_boxes", sub.max_boxes, ">= 1")
        c(0 < sub.nms_iou <= 1, where, f"[proposals.{sub_name}] nms_iou", sub.nms_iou, "(0, 1]")
        c(
            sub.work_width >= 16,
            where,
            f"[proposals.{sub_name}] work_width",
            sub.work_width,
            ">= 16 pixels",
        )
        _range(
            where,
            f"[proposals.{sub_name}] min_area_frac..max_area_frac",
            (sub.min_area_frac, sub.max_area_frac),
        )


def _check_splits(cfg: Config, where: str) -> None:
    """``[splits]``: RoC-max values, the ranges of the positive and negative labels, strata."""
    c = check_value
    sp = cfg.splits
    c(
        len(sp.roc_max) > 0,
        where,
        "[splits] roc_max",
        list(sp.roc_max),
        "a non-empty list of values in [0, 1]",
    )
    c(
        all(0 <= r <= 1 for r in sp.roc_max),
        where,
        "[splits] roc_max",
        list(sp.roc_max),
        "values in [0, 1]",
    )
    c(
        len(set(sp.roc_max)) == len(sp.roc_max),
        where,
        "[splits] roc_max",
        list(sp.roc_max),
        "distinct values",
    )
    _range(where, "[splits] pos_roc", sp.pos_roc)
    _range(where, "[splits] pos_sob", sp.pos_sob)
    _range(where, "[splits] neg_sob", sp.neg_sob)
    c(
        0 <= sp.neg_roc_min <= min(sp.roc_max),
        where,
        "[splits] neg_roc_min",
        sp.neg_roc_min,
        f"[0, min(roc_max) = {min(sp.roc_max)}]",
    )
    st_ = sp.sob_strata
    c(
        len(st_) >= 2
        and all(a < b for a, b in itertools.pairwise(st_))
        and st_[0] >= 0
        and st_[-1] <= 1,
        where,
        "[splits] sob_strata",
        list(st_),
        "at least two increasing edges in [0, 1]",
    )


def _check_report(cfg: Config, where: str) -> None:
    """``[report]``: bootstrap, interval, chance draws, the page's options, a second radius."""
    c = check_value
    rp = cfg.report
    c(
        rp.bootstrap >= 0,
        where,
        "[report] bootstrap",
        rp.bootstrap,
        ">= 0 resamples (0: no intervals)",
    )
    c(0 < rp.ci < 1, where, "[report] ci", rp.ci, "(0, 1), e.g. 0.95")
    c(
        rp.chance_draws >= 200,
        where,
        "[report] chance_draws",
        rp.chance_draws,
        ">= 200 random orders (SPEC 9: the floor is measured, not the positive rate)",
    )
    c(
        type(rp.min_positive_images) is int and rp.min_positive_images >= 1,
        where,
        "[report] min_positive_images",
        rp.min_positive_images,
        "an integer >= 1 (query images holding a positive before a figure earns a verdict)",
    )
    c(rp.gallery >= 0, where, "[report] gallery", rp.gallery, ">= 0 thumbnails per method and kind")
    c(
        0 <= rp.headline_roc_max <= 1,
        where,
        "[report] headline_roc_max",
        rp.headline_roc_max,
        "[0, 1] (the page falls back to the largest RoC-max written)",
    )
    c(rp.locmap_examples >= 0, where, "[report] locmap_examples", rp.locmap_examples, ">= 0")
    c(
        rp.gt_radius_also >= 0
        and rp.gt_radius_also != cfg.retrieval.gt_radius_m
        and (rp.gt_radius_also == 0 or rp.gt_radius_also >= cfg.retrieval.db_stride_m / 2),
        where,
        "[report] gt_radius_also",
        rp.gt_radius_also,
        "0 (off) or a second place radius in metres, other than [retrieval] gt_radius_m and at "
        "least half of [retrieval] db_stride_m",
    )


def _check_detect(cfg: Config, where: str) -> None:
    """``[detect]`` (SPEC 13.1), then ``[report] recall_at``."""
    c = check_value
    rp = cfg.report
    dt = cfg.detect
    c(
        dt.boxes in BOX_GENERATORS,
        where,
        "[detect] boxes",
        dt.boxes,
        f"one of {', '.join(BOX_GENERATORS)} (SPEC 13.1)",
    )
    c(
        dt.box_score in BOX_SCORES,
        where,
        "[detect] box_score",
        dt.box_score,
        f"one of {', '.join(BOX_SCORES)}",
    )
    c(0 < dt.alarm < 1, where, "[detect] alarm", dt.alarm, "(0, 1): a false-alarm rate")
    c(
        dt.localizer in DETECT_LOCALIZERS,
        where,
        "[detect] localizer",
        dt.localizer,
        " or ".join(DETECT_LOCALIZERS),
    )
    check_local(dt.local, f"{where} [detect.local]")
    c(
        dt.box_prior in BOX_PRIORS,
        where,
        "[detect] box_prior",
        dt.box_prior,
        " or ".join(BOX_PRIORS),
    )
    c(
        0 < dt.locmap_level < 1,
        where,
        "[detect] locmap_level",
        dt.locmap_level,
        "(0, 1): a share of each frame's LoC range",
    )
    c(
        0 <= dt.min_box_side < 1e4,
        where,
        "[detect] min_box_side",
        dt.min_box_side,
        "pixels a side, >= 0 (0: keep every box)",
    )
    c(
        len(rp.recall_at) > 0
        and all(n >= 1 for n in rp.recall_at)
        and list(rp.recall_at) == sorted(set(rp.recall_at)),
        where,
        "[report] recall_at",
        list(rp.recall_at),
        "a non-empty increasing list of list positions >= 1, e.g. [1, 5, 10, 20]",
    )


def _check_fixture_keys(cfg: Config, where: str) -> None:
    """``[fixture]`` (:func:`check_fixture`) and its formats, one or one per session."""
    c = check_value
    fx = cfg.fixture
    check_fixture(fx, where)
    c(
        not fx.formats or len(fx.formats) in (1, len(cfg.sessions)),
        where,
        "[fixture] formats",
        list(fx.formats),
        f"one format, or one per session ({len(cfg.sessions)})",
    )
    c(
        all(f in FIXTURE_FORMATS for f in fx.formats),
        where,
        "[fixture] formats",
        list(fx.formats),
        f"names from {list(FIXTURE_FORMATS)}",
    )


#: The log formats the fixture generator writes (``harness.fixture.generate.FORMATS``).
FIXTURE_FORMATS = ("nclt", "ros1", "ros2", "mcap", "ros2mcap", "mcaptf")


def _device(device: str, where: str, key: str) -> None:
    """A CUDA device asked for by name must exist on this machine (``auto`` falls back)."""
    if not device.startswith("cuda"):
        return
    import torch

    if not torch.cuda.is_available():
        raise ConfigError(
            f"{where}: {key} = {device!r}, but torch sees no CUDA device on this machine; use "
            "'auto' (CUDA where there is one, else the CPU) or 'cpu'"
        )


def check_local(lc: LocalConfig, where: str) -> LocalConfig:
    """``lc`` unchanged, after checking every option (one ConfigError naming the first bad one)."""
    check_value(
        len(lc.align) > 0 and all(a in ALIGNERS for a in lc.align)
        and len(set(lc.align)) == len(lc.align),
        where, "align", list(lc.align), f"a chain of distinct {', '.join(ALIGNERS)}",
    )  # fmt: skip
    check_value(lc.keypoints in KEYPOINTS, where, "keypoints", lc.keypoints, " or ".join(KEYPOINTS))
    check_value(lc.image in FEATURE_IMAGES, where, "image", lc.image, " or ".join(FEATURE_IMAGES))
    check_value(lc.max_keypoints >= 50, where, "max_keypoints", lc.max_keypoints, ">= 50")
    check_value(lc.min_inliers >= 4, where, "min_inliers", lc.min_inliers, ">= 4")
    check_value(
        0 < lc.max_corner_shift <= 1, where, "max_corner_shift", lc.max_corner_shift, "(0, 1]"
    )
    check_value(-1 <= lc.ecc_min_cc <= 1, where, "ecc_min_cc", lc.ecc_min_cc, "[-1, 1]")
    check_value(
        -1 <= lc.identity_min_ncc <= 1, where, "identity_min_ncc", lc.identity_min_ncc, "[-1, 1]"
    )
    check_value(0 <= lc.grow <= 4, where, "grow", lc.grow, "[0, 4]")
    check_value(lc.min_grow_px >= 1, where, "min_grow_px", lc.min_grow_px, ">= 1")
    check_value(0 <= lc.tolerance <= 1, where, "tolerance", lc.tolerance, "[0, 1]")
    check_value(lc.min_tolerance_px >= 0, where, "min_tolerance_px", lc.min_tolerance_px, ">= 0")
    check_value(
        lc.window_over_tolerance >= 1,
        where,
        "window_over_tolerance",
        lc.window_over_tolerance,
        ">= 1",
    )
    check_value(lc.work_side >= 32, where, "work_side", lc.work_side, ">= 32")
    check_value(lc.align_side >= 32, where, "align_side", lc.align_side, ">= 32")
    check_value(lc.max_template_px >= 4, where, "max_template_px", lc.max_template_px, ">= 4")
    check_value(lc.frames_per_unit >= 1, where, "frames_per_unit", lc.frames_per_unit, ">= 1")
    return lc
