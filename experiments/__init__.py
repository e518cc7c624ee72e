"""experiments."""
from scr_env.installation import check_control_package

check_control_package(strict=True)  # every experiment needs this project's `control`, not python-control
