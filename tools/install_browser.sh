#!/usr/bin/env bash
# Debian's headless Chromium and ChromeDriver for the flight review page's browser test (make test).
# Where they cannot be installed (no apt-get, not root, no registry), that test skips and says why.
set -uo pipefail
if command -v chromium >/dev/null && command -v chromedriver >/dev/null; then
  exit 0
fi
if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
  echo "browser: installing Debian's chromium and chromium-driver for the flight review test (about a minute)"
  if { timeout 600 apt-get update -qq && timeout 900 apt-get install -y -qq chromium chromium-driver; } >/dev/null 2>&1; then
    echo "browser: done"
  else
    echo "browser: chromium not installed; the flight review browser test will skip"
  fi
else
  echo "browser: chromium not installed (needs apt-get as root); the flight review browser test will skip"
fi
exit 0
