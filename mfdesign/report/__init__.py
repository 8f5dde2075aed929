"""Reports: HTML pages (with their pictures and a JSON twin) of what the layers upstream found.

The report layer renders; it computes nothing new. Calibration and diagnosis produce the
numbers, words and posteriors; the commands (``mfdesign demo``, ``mfdesign diagnose``)
hand them here:

* :mod:`~mfdesign.report.render`: the one HTML writer: Jinja templates (package data,
  ``templates/*.html.j2``, autoescaped) that all extend ``base.html.j2``;
* :mod:`~mfdesign.report.sections`: :class:`Report`, titled sections of text, a table and
  pictures (``index.html`` + ``report.json``: the demo's report);
* :mod:`~mfdesign.report.diagnosis`: a diagnosis's pictures, ``index.html`` and
  ``diagnosis.json`` (:func:`~mfdesign.report.diagnosis.write_report`).
"""

from mfdesign.report.render import write_html
from mfdesign.report.sections import Report, Section

__all__ = ["Report", "Section", "write_html"]
