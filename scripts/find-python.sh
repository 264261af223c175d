#!/usr/bin/env bash
# Print the path of a Python >= 3.12, following docs/cli.md ("Finding Python >= 3.12"):
# $PYTHON if set; else the first of python3.13, python3.12, python3 that runs and
# reports >= 3.12; else $(pyenv root)/versions/3.1[2-9]*/bin/python3; else fail.
set -u
ok() { "$1" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 12) else 1)' >/dev/null 2>&1; }
if [ -n "${PYTHON:-}" ]; then
  if ok "$PYTHON"; then echo "$PYTHON"; exit 0; fi
  echo "error: \$PYTHON=$PYTHON is not a working Python >= 3.12" >&2; exit 1
fi
for cand in python3.13 python3.12 python3; do
  if command -v "$cand" >/dev/null 2>&1 && ok "$cand"; then command -v "$cand"; exit 0; fi
done
if command -v pyenv >/dev/null 2>&1; then
  root=$(pyenv root 2>/dev/null)
  for cand in $(ls -d "$root"/versions/3.1[2-9]* 2>/dev/null | sort -V); do
    if ok "$cand/bin/python3"; then echo "$cand/bin/python3"; exit 0; fi
  done
fi
echo "error: lmpromp-ppl needs Python >= 3.12 (ArviZ 1.x); install python3.12 or set \$PYTHON" >&2
exit 1
