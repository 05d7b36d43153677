#!/usr/bin/env bash
# Prints a Python 3.10 of this machine, the oldest Python the esrp package supports: $PYTHON310,
# python3.10 on PATH, or pyenv's; prints nothing (and exits 1) when there is none. Used by
# scripts/python-tests.sh (the client's suite on 3.10) and scripts/docker-tests.sh (the wheels on 3.10).
for candidate in ${PYTHON310:-} python3.10 "$HOME"/.pyenv/versions/3.10.*/bin/python; do
    if "$candidate" -c 'import sys; assert sys.version_info[:2] == (3, 10)' >/dev/null 2>&1; then
        echo "$candidate"
        exit 0
    fi
done
exit 1
