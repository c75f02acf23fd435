"""Mechanism descriptions: frozen data loaded from TOML model files. Imports nothing from exuflex."""

from .dofs import COMPONENTS, LINK_FRAME, DofRef, ElasticDofs, elastic_dofs
from .limits import MAX_DAMPING_RATIO, MAX_ELEMENTS, MAX_STIFFNESS_RATIO, remeshed_element_count
from .loader import ModelFileError, load_manoeuvre, load_mechanism, parse_mechanism, read_samples
from .refine import refine_mechanism, remesh_mechanism
from .spec import (
    Coordinate,
    Damping,
    Joint,
    Link,
    LinkPoint,
    LumpedMass,
    Manoeuvre,
    Material,
    Mechanism,
    Motor,
    ObserverSpec,
    ReductionSpec,
    Section,
    Sensor,
)

__all__ = [
    "COMPONENTS",
    "Coordinate",
    "Damping",
    "ElasticDofs",
    "Joint",
    "Link",
    "LinkPoint",
    "LumpedMass",
    "Manoeuvre",
    "Material",
    "Mechanism",
    "ModelFileError",
    "Motor",
    "ObserverSpec",
    "ReductionSpec",
    "Section",
    "Sensor",
    "elastic_dofs",
    "DofRef",
    "LINK_FRAME",
    "MAX_DAMPING_RATIO",
    "MAX_ELEMENTS",
    "MAX_STIFFNESS_RATIO",
    "remeshed_element_count",
    "load_manoeuvre",
    "load_mechanism",
    "parse_mechanism",
    "read_samples",
    "refine_mechanism",
    "remesh_mechanism",
]
