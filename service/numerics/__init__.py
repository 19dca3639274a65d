"""The numerics wing: everything that computes, and nothing that talks to the world.

calib (estimators, alignment, tensor, coverage, model order, the site field), effects (one small class
per physical effect), engine (the effects fit), diagnose (what is missing), noise, outputs and
decimate. Imports only numpy, scipy and drivers' data types (SampleBlock, the error tree); a test
(tests/e2e/test_layout.py) keeps it so.
"""
