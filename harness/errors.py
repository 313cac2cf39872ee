"""Error classes.

Library code raises these; the CLI maps them to exit code 1 with one clear line.
"""

from __future__ import annotations


class HarnessError(Exception):
    """Base class of every error the harness raises on purpose."""


class ConfigError(HarnessError):
    """A configuration file or option is missing, misspelled or out of range."""


class IngestError(HarnessError):
    """A season log cannot be turned into a frame table (names the file and what is wrong)."""


class CorruptLogError(IngestError):
    """A log is truncated or damaged part-way; ``messages_read`` were readable before the damage."""

    def __init__(
        self, path: object, messages_read: int, detail: str, salvage: bool = False
    ) -> None:
        self.path = path
        self.messages_read = messages_read
        self.detail = detail
        advice = (
            "--salvage was given, but nothing before the damage could be kept"
            if salvage and messages_read == 0
            else "--salvage was given"
            if salvage
            else "Rerun with --salvage to keep the frames read before the damage."
        )
        super().__init__(
            f"{path}: log is truncated or corrupt ({detail}); {messages_read} messages were "
            f"read before the damage. {advice}"
        )


class TopicError(IngestError):
    """An image or pose topic is missing or ambiguous."""


class AnnotationError(HarnessError):
    """An annotation or proposal table has a bad row (names the file and row)."""


class OwnershipError(HarnessError):
    """An output path exists and was not written by the harness (or needs ``--force``)."""


class CacheError(HarnessError):
    """A cached stage output is unreadable or inconsistent with its manifest."""


class RetrievalError(HarnessError):
    """Descriptors or imported rank lists are inconsistent."""
