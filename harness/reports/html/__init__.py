"""The report page: its tables, figures and the one HTML file.

The rendering API other pages use (``harness detect``'s): :func:`esc` escapes a value for HTML,
:data:`SCRIPT` is the script by which a page reports its own loaded images (the browser test).
"""

from harness.reports.html.cells import esc
from harness.reports.html.page import SCRIPT

__all__ = ["SCRIPT", "esc"]
