"""``harness detect``: change boxes and frames with calibrated scores, Table D and its page."""
