if __name__ != "uwdock.datasets":  # this folder reached as a top-level name (the working directory)
    raise ImportError(
        "this folder is installed as uwdock.datasets: import uwdock.datasets "
        "(pip install -e . from the repository puts it there)"
    )
