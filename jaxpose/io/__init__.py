"""File readers and writers: g2o pose graphs and BAL bundle-adjustment problems.

All readers return plain float64/int64 numpy containers (:class:`PoseGraph`,
:class:`BALProblem`) and raise :class:`FormatError` (``"FILE:LINE: ..."``) on malformed input.
``INFORMATION_POLICIES``: the policies for information matrices that are not positive
definite (:func:`apply_information_policy`, ``read_g2o(information=...)``). The BAL camera
model itself is :func:`jaxpose.geometry.bal_project`.
"""

from ._bal import BALProblem, read_bal, write_bal
from ._errors import FormatError
from ._g2o import (
    INFORMATION_POLICIES,
    PoseGraph,
    apply_information_policy,
    connected_components,
    read_g2o,
    write_g2o,
)

__all__ = [
    "BALProblem",
    "FormatError",
    "INFORMATION_POLICIES",
    "PoseGraph",
    "apply_information_policy",
    "connected_components",
    "read_bal",
    "read_g2o",
    "write_bal",
    "write_g2o",
]
