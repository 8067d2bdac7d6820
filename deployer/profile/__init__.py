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
    PROTOCOL_MAX_READ,
    PROTOCOL_MAX_WRITE,
    Access,
    Addressing,
    CommitAction,
    HealthCheck,
    IdentityCheck,
    Limits,
    Parameter,
    Precondition,
    Profile,
    WriteAction,
)

__all__ = [
    "PROTOCOL_MAX_READ",
    "PROTOCOL_MAX_WRITE",
    "Access",
    "Addressing",
    "CommitAction",
    "HealthCheck",
    "IdentityCheck",
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
    "parse_register",
    "profile_ref",
    "resolve_profile",
    "wire_address",
]
