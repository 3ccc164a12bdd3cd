"""The discrepancy workflow: find where the physics model
and the measurements disagree, name the missing effect, add it, show the gap shrink.

* :mod:`.noise`: the noise floor from the data;
* :mod:`.localise`: where the residual exceeds it;
* :mod:`.search`: candidates, held-out scores, the screw family;
* :mod:`.significance`: the test that names an effect, BIC;
* :mod:`.workflow`: the loop (:func:`run_diagnosis`);
* :mod:`.job`: the job behind the command (:func:`diagnose`): the config checked, files in and out;
* :mod:`.report`: report.md, figures, the terminal verdict;
* :mod:`.hidden`: datasets with a hidden effect (tests, benchmark).
"""

from .job import diagnose
from .workflow import DiagnoseError, run_diagnosis

__all__ = ["DiagnoseError", "diagnose", "run_diagnosis"]
