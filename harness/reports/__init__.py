"""Reports: the run's tables (markdown, CSV, LaTeX), Table L, plots and the page."""
