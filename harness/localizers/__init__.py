"""Method §11's outside localizers: the task export (stages: ``pipeline.localizer_stages``)."""
