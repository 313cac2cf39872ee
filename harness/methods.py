"""Method ids, labels, registries, the localizer name rule: the bottom of the house.

Every module that needs to know what a fusion or proposal method is called, how it is labelled
or whether a name is known reads it here, so the config check, the fusion stage, the reports and
the figures share one catalogue and none of them imports another to ask. The functions behind
the names live with their stage (``fusion``, ``proposals``), which register them here.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import Any, TypeVar

T = TypeVar("T")
F = TypeVar("F", bound=Callable[..., Any])


class Registry(dict[str, T]):
    """One extension point's entries by name, the harness's own and a user's alike.

    Every registry of the harness is one: fusion rules, proposers and their options, localizer
    kinds, log formats, report tables, descriptors. It is a dict, so every reader reads it as
    one; an entry comes in through :meth:`add` (or :meth:`entry`, the same as a decorator), which
    refuses a name already taken, among the entries or the names ``reserved`` beside them.
    """

    def __init__(self, what: str, reserved: Iterable[str] = ()) -> None:
        super().__init__()
        self.what = what
        self.reserved = tuple(reserved)

    def add(self, name: str, entry: T, error: type[Exception] = ValueError) -> T:
        """Add ``entry`` as ``name`` and return it.

        Raises:
            ValueError: ``name`` is taken (``error`` instead, where the caller gives one).
        """
        if name in self or name in self.reserved:
            raise error(
                f"{self.what} {name!r} exists (the name is taken); known: {[*self, *self.reserved]}"
            )
        self[name] = entry
        return entry

    def entry(self, name: str) -> Callable[[T], T]:
        """:meth:`add` as a decorator: ``@REGISTRY.entry("name")`` above the entry."""

        def register(obj: T) -> T:
            return self.add(name, obj)

        return register


@dataclass(frozen=True)
class FusionRule:
    """One fusion method of the catalogue: its name, label, what it needs and where it may run.

    Built-in and registered methods are the same record (``fusion.register_fusion_rule`` makes one);
    the function behind a ``cover`` rule is attached by the module that defines it
    (``harness.fusion.rules``), so this module still imports nothing of the harness.
    """

    name: str
    label: str
    #: ``cover``: a function of the cover matrix (fused set); ``image``: of the image alone
    #: (``size_prior``, ``random``); ``unfused``: one sample per original box.
    kind: str = "cover"
    #: ``table``: one of Table I's six rows; ``extra``: the variants-and-baselines block.
    block: str = "extra"
    #: Needs the relevance score ``d`` (a localizer without one cannot have it).
    needs_score: bool = False
    #: Needs the rank-list lengths ``L`` (``r' = (L + 1 - rank) / L``).
    needs_lengths: bool = False
    #: Defined on the box list of all localizers together (method §11).
    across: bool = True
    #: ``harness detect`` may threshold its LoC into boxes.
    detect: bool = False
    #: Reads no pixel: method §7's confound warning compares it with Table I's six.
    baseline: bool = False
    #: The keyword options its function takes: ``seed`` (the image's seed), ``rrf_c``.
    options: tuple[str, ...] = ()
    #: The function: (cover (m, n) bool, r (n,), d (n,), L (n,)) -> (m,) LoC; None until attached.
    loc: Callable[..., Any] | None = None


def _builtin(name: str, label: str, **kw: Any) -> FusionRule:
    return FusionRule(name, label, **kw)


_RANK = {"needs_lengths": True}
#: Every fusion method, in table order: method §7's six (Table I's rows), the paper's two
#: variants, the field's four rules (method §14), the three baselines; then registered ones.
FUSION_RULES: Registry[FusionRule] = Registry("fusion method")
for _rule in (
    _builtin("rank_fusion", "rank fusion", block="table", detect=True, **_RANK),
    _builtin(
        "rank_fusion_le2",
        "rank fusion (<=2)",
        block="table",
        detect=True,
        options=("seed",),
        **_RANK,
    ),
    _builtin(
        "rank_fusion_le3",
        "rank fusion (<=3)",
        block="table",
        detect=True,
        options=("seed",),
        **_RANK,
    ),
    _builtin("rank_no_fusion", "rank w/o fusion", kind="unfused", block="table", across=False),
    _builtin("score_max", "score max", block="table", needs_score=True, across=False),
    _builtin("score_sum", "score sum", block="table", needs_score=True, across=False),
    _builtin("rank_fusion_asc", "rank fusion asc (variant 2)"),
    _builtin("rank_fusion_raw", "rank fusion raw (variant 1)", **_RANK),
    _builtin("rrf", "RRF (reciprocal rank)", detect=True, options=("rrf_c",), **_RANK),
    _builtin("combmnz", "CombMNZ", detect=True, **_RANK),
    _builtin("borda", "Borda count", detect=True, **_RANK),
    _builtin("isr", "ISR (inverse square rank)", detect=True, **_RANK),
    _builtin("size_prior", "size prior (no pixel)", kind="image", baseline=True),
    _builtin("cover_count", "cover count (no pixel)", baseline=True),
    _builtin("random", "random", kind="image", baseline=True),
):
    FUSION_RULES.add(_rule.name, _rule)


def rules_where(**flags: Any) -> tuple[str, ...]:
    """The catalogue's methods (registered ones too) whose record has every given field value."""
    return tuple(
        n for n, r in FUSION_RULES.items() if all(getattr(r, k) == v for k, v in flags.items())
    )


#: Table I's six rows, in method §7's order.
FUSION_METHODS = rules_where(block="table")
#: The paper's two variants, the field's four rules and the three baselines (method §7 and
#: 14), the separate block of every table.
EXTRA_METHODS = rules_where(block="extra")
#: The field's standard rank-fusion rules (method §14): ranks alone, so every localizer
#: (imported lists without scores too) and every pair of localizers can have them.
STANDARD_RULES = ("rrf", "combmnz", "borda", "isr")
#: Baselines that read no pixel: method §7's confound warning compares them with the six.
BASELINES = rules_where(baseline=True)
ALL_METHODS = FUSION_METHODS + EXTRA_METHODS

#: How every table, figure and page names a fusion method (registered ones added as registered).
METHOD_LABELS = {n: r.label for n, r in FUSION_RULES.items()}


def is_unfused(name: str) -> bool:
    """Whether fusion rule ``name`` scores the original boxes, one sample each (``unfused``)."""
    rule = FUSION_RULES.get(name)
    return rule is not None and rule.kind == "unfused"


def unfused(methods: Iterable[str]) -> str | None:
    """The first of ``methods`` that scores the original boxes (``rank_no_fusion``), or None."""
    return next((m for m in methods if is_unfused(m)), None)


def add_rule(rule: FusionRule) -> None:
    """Put ``rule`` in the catalogue (its label too).

    Raises:
        ValueError: its name is taken.
    """
    FUSION_RULES.add(rule.name, rule)
    METHOD_LABELS[rule.name] = rule.label


@dataclass(frozen=True)
class Proposer:
    """One proposal method of the catalogue (method §5): what it reads, and its function.

    Built-in and registered methods are the same record (``proposals.register_proposer`` makes one
    that reads the image); the functions behind the built-in ones are attached by
    :mod:`harness.proposals.proposers`, so this module still imports nothing of the harness.
    """

    name: str
    #: ``frame``: boxes from the frame's size alone (``grid5``); ``image``: one upright RGB image
    #: at a time; ``batch``: a batch of images (a network: ``yolo``); ``table``: a table of the
    #: user's (``file``). The stage runs each kind its own way; the order lists them.
    reads: str = "image"
    #: It works on a copy ``[proposals.<name>] work_width`` wide, so a reduced decode gives it the
    #: same boxes (``tests/proposals/test_proposals.py``).
    reducible: bool = False
    #: What it needs of ``[proposals]``, checked at load: (the key as the error names it, its
    #: attribute path in the section, what is allowed).
    requires: tuple[tuple[str, str, str], ...] = ()
    #: ``frame``: (width, height) -> boxes (k, 4); ``image``: (rgb, [proposals]) -> (boxes,
    #: scores); ``batch``: [proposals] -> a function of a list of images; ``table``: (frames,
    #: [proposals]) -> proposal rows. None until attached.
    run: Callable[..., Any] | None = None


def proposer(name: str) -> Callable[[F], F]:
    """Attach the decorated function as the one of built-in proposal method ``name`` (its record).

    The proposals package decorates its functions with it, as :func:`harness.fusion.rules.rule`
    does the fusion rules': a built-in method is its record here and its function there.
    """

    def attach(fn: F) -> F:
        PROPOSERS[name] = replace(PROPOSERS[name], run=fn)
        return fn

    return attach


#: The order of the kinds in ``known_proposal_methods`` (and in error messages).
PROPOSER_READS = ("frame", "image", "batch", "table")
#: Proposal methods by name: built-in, then registered ones (``proposals.register_proposer``).
PROPOSERS: Registry[Proposer] = Registry("proposal method")
for _proposer in (
    Proposer("grid5", "frame"),
    Proposer("full", "frame"),
    Proposer("edges", reducible=True),
    Proposer("mser", reducible=True),
    Proposer("segments"),
    Proposer("selective"),
    Proposer(
        "yolo",
        "batch",
        requires=(
            (
                "[proposals.yolo] weights",
                "yolo.weights",
                "a local weights path (the method 'yolo' is listed)",
            ),
        ),
    ),
    Proposer(
        "file",
        "table",
        requires=(
            ("[proposals] file", "file", "a path to a box table (the method 'file' is listed)"),
        ),
    ),
):
    PROPOSERS.add(_proposer.name, _proposer)
#: A registered method's options: name -> the dataclass its ``[proposals.<name>]`` table builds.
PROPOSER_OPTIONS: Registry[type] = Registry("options of proposal method")
#: A registered fusion rule's options: name -> the dataclass its ``[fusion.<name>]`` table builds.
FUSION_OPTIONS: Registry[type] = Registry("options of fusion method")


def known_fusion_methods() -> tuple[str, ...]:
    """Every method ``[fusion] methods`` may list: method §7's, then registered ones."""
    return tuple(FUSION_RULES)


def known_proposal_methods() -> tuple[str, ...]:
    """Every proposal method name ``[proposals] methods`` may list, kind by kind (as registered)."""
    return tuple(sorted(PROPOSERS, key=lambda n: PROPOSER_READS.index(PROPOSERS[n].reads)))


def ordered_methods(methods: Iterable[str]) -> tuple[str, ...]:
    """The configured methods in table order.

    method §7's (Table I's six, the variants, the baselines), then registered ones as
    registered.
    """
    want = set(methods)
    return tuple(m for m in known_fusion_methods() if m in want)


#: A localizer's name: it heads tables and names files (never a path).
LOCALIZER_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,63}")


#: What a name that is not one is told (``[[localizers]]`` and ``--import`` alike).
LOCALIZER_NAME_RULE = (
    "1-64 ASCII letters, digits, '.', '_', '-' or '+', starting with a letter or digit"
)


def is_localizer_name(name: object) -> bool:
    """Whether ``name`` may name a localizer: one check for ``[[localizers]]`` and ``--import``."""
    return isinstance(name, str) and LOCALIZER_NAME.fullmatch(name) is not None
