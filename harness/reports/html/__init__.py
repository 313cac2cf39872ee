"""The report page: its tables, figures and the one HTML file."""
