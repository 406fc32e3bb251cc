"""Camera models, camera files, and frames & transforms (T_a_b, check_T)."""

if (
    __name__ != "uwdock.calibration"
):  # this folder reached as a top-level name (the working directory)
    raise ImportError(
        "this folder is installed as uwdock.calibration: import uwdock.calibration "
        "(pip install -e . from the repository puts it there)"
    )
