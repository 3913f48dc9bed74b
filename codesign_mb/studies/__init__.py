"""The paper's studies: Table I, Figs. 4-6, the head-to-head table, sweeps, the demos, reports.

Each study is one module that computes its results; each figure has one renderer.
"""
