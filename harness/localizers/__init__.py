"""SPEC 11's outside localizers: the task export (their stages: ``pipeline.localizer_stages``)."""
