"""Speed benchmarks. Every figure is measured beside a reference run in the same process
(Farama MiniGrid, a plain MuJoCo loop), so ratios hold on whatever machine runs them."""
