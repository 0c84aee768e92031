#!/usr/bin/env bash
# Called by `make anatomy`: install the anatomy packages (--no-deps) and regenerate the bundled limb.
exec bash "$(dirname "${BASH_SOURCE[0]}")/run.sh" "$@"
