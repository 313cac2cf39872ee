"""The fusion rules of the fused set, one module each (method §7 and 14), the ranx way.

Each module attaches its function to its record in the method catalogue
(``harness.methods.FUSION_RULES``) with :func:`.base.rule`, the same record a user's
``fusion.register_fusion_rule`` makes, so reproduce, Table L and detect find the paper's rules and a
user's in one place. Importing the package imports every module in it: a new rule is its record
and its module, nothing else.
"""

from __future__ import annotations

import importlib
import pkgutil

from harness.fusion.rules.base import Loc, r_desc_of, rule, standard_rule

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")

__all__ = ["Loc", "r_desc_of", "rule", "standard_rule"]
