"""SPEC 11's localizers: their stages and the task export for outside localizers."""
