"""Self-contained HTML pages: a run's report (which prints as the commissioning record), the
as-found record of a pull, and a fleet's drift matrix.

Each page is one file with its data, styles and script inside: no network, no CDN, it opens from a
file:// URL and prints. The data is embedded once as JSON and the tables are drawn by the page's
script (a device's parameter table when it is opened, all of them before printing), so a report of
1,000 devices x 100 parameters is a page smaller than its JSON that a browser opens at once.
"""

from .render import as_found_page, drift_page, run_page

__all__ = ["as_found_page", "drift_page", "run_page"]
