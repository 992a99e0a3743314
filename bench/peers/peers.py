#!/usr/bin/env python3
"""Peers for `rangegp-bench gp`: numpy/OpenBLAS Cholesky and scikit-learn GP on the same data.

Reads the JSON the bench writes (training inputs, targets, noise variances, queries, kernel,
Cholesky sizes) and prints JSON timings. Single-threaded BLAS (OPENBLAS_NUM_THREADS=1 is set by
the caller) so the figures compare per core with the Rust side.
"""
import json
import sys
import time

import numpy as np
import sklearn
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern


def median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main():
    spec = json.load(open(sys.argv[1]))
    rng = np.random.default_rng(0)
    chol = {}
    for n in spec["chol_sizes"]:
        a = rng.standard_normal((n, n))
        spd = a @ a.T + n * np.eye(n)
        t = median_time(lambda: np.linalg.cholesky(spd), max(3, 2048 // n))
        chol[str(n)] = (n ** 3 / 3.0) / t / 1e9
    x = np.array(spec["train_x"])
    y = np.array(spec["train_y"])
    noise = np.array(spec["noise_var"])
    xs = np.array(spec["query_x"])
    kernel = ConstantKernel(spec["variance"], constant_value_bounds="fixed") * Matern(
        length_scale=spec["length_scale"], nu=1.5, length_scale_bounds="fixed")
    holder = {}

    def fit():
        holder["gp"] = GaussianProcessRegressor(kernel=kernel, alpha=noise, optimizer=None).fit(x, y)

    def predict():
        holder["pred"] = holder["gp"].predict(xs, return_std=True)

    fit_s = median_time(fit, spec["repeats"])
    predict_s = median_time(predict, spec["repeats"])
    json.dump({"numpy": np.__version__, "sklearn": sklearn.__version__, "openblas_gflops": chol,
               "sklearn_fit_s": fit_s, "sklearn_predict_s": predict_s,
               "sklearn_mean_first": float(holder["pred"][0][0]),
               "sklearn_std_first": float(holder["pred"][1][0])}, sys.stdout)


if __name__ == "__main__":
    main()
