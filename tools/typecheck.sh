#!/usr/bin/env bash
# mypy over the installed layout: labrunner/ with drivers/ and sims/ as labrunner.drivers and
# labrunner.sims (pyproject's package-dir), which mypy cannot follow through an editable install.
# A tree of symlinks gives it that layout; errors are reported with repository paths.
set -euo pipefail
cd "$(dirname "$0")/.."
stage="$(mktemp -d)"
trap 'rm -rf "$stage"' EXIT
mkdir "$stage/labrunner"
for entry in labrunner/*; do
    ln -s "$PWD/$entry" "$stage/labrunner/$(basename "$entry")"
done
ln -s "$PWD/drivers" "$stage/labrunner/drivers"
ln -s "$PWD/sims" "$stage/labrunner/sims"
status=0
(cd "$stage" && mypy --config-file "$OLDPWD/pyproject.toml" -p labrunner) > "$stage/out.txt" 2>&1 || status=$?
sed -e 's#^labrunner/drivers/#drivers/#' -e 's#^labrunner/sims/#sims/#' "$stage/out.txt"
exit $status
