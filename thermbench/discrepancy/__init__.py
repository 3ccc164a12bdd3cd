"""The discrepancy workflow (issue "Discrepancy workflow"): find where the physics model
and the measurements disagree, name the missing effect, add it, show the gap shrink.

* :mod:`.noise`: the noise floor from the data;
* :mod:`.localise`: where the residual exceeds it;
* :mod:`.search`: candidates, held-out scores, BIC and the test;
* :mod:`.workflow`: the loop (:func:`run_diagnosis`) and the job (:func:`diagnose`);
* :mod:`.report`: report.md, figures, the terminal verdict;
* :mod:`.hidden`: datasets with a hidden effect (tests, benchmark).
"""

from .workflow import DiagnoseError, diagnose, run_diagnosis

__all__ = ["DiagnoseError", "diagnose", "run_diagnosis"]
