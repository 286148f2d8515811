#!/usr/bin/env bash
# Make sure Debian's chromium is installed, for the dashboard's browser tests (playwright drives it
# through executable_path; playwright's own browser download is never used).
set -euo pipefail
if command -v chromium >/dev/null 2>&1; then
    exit 0
fi
if [ "$(id -u)" = 0 ]; then
    SUDO=""
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    SUDO="sudo -n"
else
    echo "install_chromium: chromium is missing and this user cannot run apt-get; install Debian's chromium package" >&2
    exit 1
fi
log=$(mktemp)
if ! { $SUDO apt-get update && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y --no-install-recommends chromium; } >"$log" 2>&1; then
    cat "$log" >&2
    echo "install_chromium: apt-get install chromium failed (log above)" >&2
    exit 1
fi
echo "install_chromium: $(chromium --version 2>/dev/null || echo chromium installed)"
