"""benchmarks/native_profile.py's reading of py-spy's raw stacks (the profile itself needs py-spy)."""

from scripts import load_script


def test_native_profile_splits_compiled_loops_from_the_rest_by_stage():
    """Samples inside measure_object are split into the compiled loops (a _kernels frame below the innermost Python
    frame) and the rest, by the function _measure called, the rest also by its innermost line of shearfit; samples
    outside measure_object and the profiles' first build (fast_pair) are left out."""
    mod = load_script("benchmarks/native_profile.py")
    top = "<module> (child.py:9);measure_object (shearfit/engine/measure.py:149);_measure (shearfit/engine/measure.py:229)"
    raw = [
        top + ";adaptive_samples (shearfit/engine/sampling.py:900);sample_chunk (shearfit/engine/_kernels.c:1);"
              "make_bins (shearfit/engine/_kernels.c:2) 30",
        top + ";adaptive_samples (shearfit/engine/sampling.py:901);e_key (shearfit/engine/sampling.py:57);"
              "PyArray_Round (numpy/_multiarray_umath.so) 10",
        top + ";join_exposures (shearfit/engine/likelihood.py:580);_fold_groups (shearfit/engine/likelihood.py:439) 5",
        "<module> (child.py:3);load (pickle.py:1) 50",
        top + ";fast_pair (shearfit/engine/profiles.py:778);__init__ (shearfit/engine/profiles.py:700) 40",
        "",
    ]
    total, compiled, stages, lines = mod.aggregate(raw, 5)
    assert total == 45 and compiled == 30
    assert stages == {"adaptive_samples": (10, 30), "join_exposures": (5, 0)}
    assert lines == [("e_key (sampling.py:57)", 10), ("_fold_groups (likelihood.py:439)", 5)]
