"""Moved to `efem_viz.prior.analytic` (transitional re-export while the tests move; removed before landing)."""

from efem_viz.prior.analytic import SpherePriorConfig, make_sphere_prior, make_sphere_scene  # noqa: F401
