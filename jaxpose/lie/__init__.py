from .base import LieAlgebra, LieGroup
from .se3 import SE3, se3
from .so3 import SO3, so3
