# Sourced by the scripts that run on a lent device machine (benchmarks/gpu_train.sh; gpu_check.sh
# may source it too): makes `import polrig.models` work from a bare checkout.
#
#   . benchmarks/polrig_path.sh FOLDER      # FOLDER: a scratch folder of the run
#
# polrig is not installed there, and its top-level models/, sim/, calibration/ and drivers/ folders
# are the packages polrig.models, polrig.sim, ... (pyproject.toml package-dir): since the layering
# (one import name), PYTHONPATH=$PWD alone no longer finds them. A folder of links gives them
# those names, as an install does, and goes first on PYTHONPATH. Source it from the repository
# root, then run python from another folder (FOLDER): python puts its working folder first on
# sys.path, and the root's own polrig/ (without those packages) would hide the links.
polrig_shim="$1/shim/polrig"
mkdir -p "$polrig_shim"
for f in "$PWD"/polrig/*; do ln -sfn "$f" "$polrig_shim/"; done
for d in models sim calibration drivers; do ln -sfn "$PWD/$d" "$polrig_shim/$d"; done
export PYTHONPATH="$1/shim${PYTHONPATH:+:$PYTHONPATH}"
