"""The compensator beside the machine (OPC UA) and a simulated CNC to close the loop on.

* :mod:`.nodes`: ``nodes.yaml``, the machine's node ids for the model's inputs and outputs;
* :mod:`.control`: one cycle without I/O (input guard, model step, error line, rate limit);
* :mod:`.settings`: the config keys the cycle uses, read and checked; :mod:`.errorline`: the error line's form;
* :mod:`.deadlines`: a control loop's schedule on absolute deadlines;
* :mod:`.client`: ``thermbench compensator``, the loop of one machine axis;
* :mod:`.opcua`: the OPC UA session (security, node checks, guarded writes);
* :mod:`.cyclelog`: the cycle log, run statistics and status line every front end shares;
* :mod:`.simcnc`: ``thermbench sim-cnc``, the asyncua server running the simulator;
* :mod:`.certs`: ``thermbench certs``, self-signed certificates for Basic256Sha256.
"""

from .client import run_compensator
from .errors import CompensatorError, RefusedWrite
from .control import Flags
from .nodes import NodesError
from .simcnc import SimCncError

__all__ = ["CompensatorError", "Flags", "NodesError", "RefusedWrite", "SimCncError", "run_compensator"]
