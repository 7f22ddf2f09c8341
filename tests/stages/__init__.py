"""Tests of qr_cl.stages: each kernel against its float64 twin (stages/<stage>_ref.py), launch shapes."""
