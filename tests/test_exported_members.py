"""The public surface, pinned (as httpx's tests/test_exported_members.py): a change to it is a decision."""

from __future__ import annotations

import inspect
import subprocess
import sys

import deployer
from deployer import api

PUBLIC = [
    "LIMITS", "Agent", "AgentError", "ApplyOptions", "BadURL", "Bound", "CodecError", "Declined", "DeployerError",
    "DeviceResult", "DeviceURL", "Drift", "FleetDevice", "FromDefault", "IdentityMismatch", "InputError", "Inventory",
    "Job", "Locked", "ParameterResult", "Plan", "PreparedRun", "Profile", "ReadJob", "Recipe", "Report",
    "RunInterrupted", "RunRequest", "RunStatus", "StalePlan", "Step", "TransportError", "UsageError", "address_text",
    "apply",
    "apply_async", "apply_fleet", "apply_fleet_async", "builtin_profiles", "check_folder", "check_output", "confirm",
    "confirm_outcome", "defaults_diff", "describe_url", "device_url", "diff", "diff_async", "diff_values", "duration",
    "file_name", "fleet_jobs", "forget_learned", "import_csv", "import_sunspec", "import_sunspec_chain",
    "import_wb_template", "import_xlsx", "imported_profile", "inventory_from", "learned_limits", "load_inventory",
    "load_plan", "load_profile", "load_recipe", "non_default", "out_of_range", "plan", "plan_async", "plan_cost",
    "plan_fleet", "plan_fleet_async", "plan_frames", "plan_to_json", "plan_values", "prepare_run", "probe",
    "profile_csv", "profile_skeleton", "profile_table", "pull", "pull_async", "pull_jobs", "pull_names",
    "pulled_recipe", "read_fleet", "read_fleet_async", "read_jobs", "read_report", "recipe_from", "register_address",
    "report_from_json", "report_text", "resolve_run", "run_fleet", "run_fleet_async", "run_info", "run_prepared",
    "run_prepared_async", "run_status", "safe_options", "scan", "serial_ports", "snapshot_text", "sunspec_models",
    "sunspec_reported", "taught_recipe", "url_option", "user_name", "validate_file", "write_output", "writing_caches",
]


def test_the_exported_names_are_pinned() -> None:
    assert api.__all__ == PUBLIC  # sorted: classes, then functions
    assert deployer.__all__ is api.__all__  # one list


def test_every_exported_name_resolves_from_the_package() -> None:
    for name in api.__all__:
        assert getattr(deployer, name) is getattr(api, name), name
    assert set(api.__all__) <= set(dir(deployer))


def test_every_exported_function_and_class_is_documented() -> None:
    for name in api.__all__:
        obj = getattr(api, name)
        assert inspect.getdoc(obj), name


def test_sync_functions_that_raise_say_so() -> None:
    """A sync entry point that can raise documents what (a Raises section)."""
    for name in ("apply", "apply_fleet", "confirm", "device_url", "diff", "inventory_from", "plan", "plan_fleet",
                 "pull",
                 "read_fleet", "read_report", "recipe_from", "run_fleet", "prepare_run", "run_prepared",
                 "validate_file", "pull_jobs", "check_folder",
                 "plan_frames", "confirm_outcome", "run_status", "resolve_run",
                 "snapshot_text", "profile_csv", "import_csv", "import_xlsx", "import_wb_template",
                 "imported_profile"):
        assert "Raises:" in (getattr(api, name).__doc__ or ""), name


def test_exported_errors_are_the_error_tree() -> None:
    from deployer import errors

    for name in api.__all__:
        obj = getattr(api, name)
        if inspect.isclass(obj) and issubclass(obj, BaseException):
            assert obj is getattr(errors, name) and issubclass(obj, errors.DeployerError)


def test_load_profile_means_one_thing() -> None:
    from deployer import profile

    assert deployer.load_profile is profile.load_profile
    assert deployer.load_profile("example-inverter").id == "example-inverter"


def test_importing_the_package_does_not_load_the_api() -> None:
    code = ("import sys, deployer\nfrom deployer import errors\n"
            "print('deployer.api' in sys.modules, deployer.__version__ != '')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.split() == ["False", "True"]
