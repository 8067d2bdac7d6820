"""Device profiles: the object dictionary of one device type (where each parameter lives).

``model`` holds the data, ``loader`` reads profile files, ``csv_import`` and ``sunspec``
turn vendors' register maps into profile files.
"""

from .loader import (
    builtin_profile,
    builtin_profile_ids,
    is_profile_path,
    load_profile,
    load_profile_file,
    parse_register,
    profile_ref,
    resolve_profile,
    wire_address,
)
from .model import (
    IDENTITY_OBJECTS,
    PROTOCOL_MAX_READ,
    PROTOCOL_MAX_WRITE,
    Access,
    Addressing,
    CommitAction,
    HealthCheck,
    IdentityCheck,
    IdentityObject,
    Limits,
    Parameter,
    Precondition,
    Profile,
    WriteAction,
    object_name,
)

__all__ = [
    "IDENTITY_OBJECTS",
    "PROTOCOL_MAX_READ",
    "PROTOCOL_MAX_WRITE",
    "Access",
    "Addressing",
    "CommitAction",
    "HealthCheck",
    "IdentityCheck",
    "IdentityObject",
    "Limits",
    "Parameter",
    "Precondition",
    "Profile",
    "WriteAction",
    "builtin_profile",
    "builtin_profile_ids",
    "is_profile_path",
    "load_profile",
    "load_profile_file",
    "object_name",
    "parse_register",
    "profile_ref",
    "resolve_profile",
    "wire_address",
]
