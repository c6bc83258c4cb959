"""Scaling benchmark (issue 5 item 4): response build, set-up and draw cost of each sampler path.

Usage::

    python benchmarks/scale.py              # default grid (~15 min on 2 cores)
    python benchmarks/scale.py --quick      # tiny grid (< 2 min)
    python benchmarks/scale.py --only l100-a37-t240-24h-f2
    python benchmarks/scale.py --hera       # the issue rows (HERA_GRID, redundancy-compressed; ~1 h loaded)
    python benchmarks/scale.py --only l200-a37-t10-8h-f1-red   # one issue row
    SCALE_PATHS=cgMF-mb python benchmarks/scale.py --only l150-a331-t30-8h-f1-red  # some paths of an issue row
    python benchmarks/scale.py --one CONFIG --json   # one configuration (used internally)

Every configuration runs in its own subprocess so ``ru_maxrss`` is that configuration's
peak resident memory.  A configuration is named ``l{lmax}-a{nants}-t{nlst}-{hours}h-f{nfreq}``:
hexagonal array of 10 / 37 / 91 / 331 antennas (rows 3-4-3, 4..7..4, 6..11..6, 11..21..11; 14.6 m), a
Gaussian 14 m dish beam, ``nlst`` equally spaced LSTs over ``hours`` (24 h: full day,
endpoint excluded, so the m-mode path applies when Nt > 2 lmax), ``nfreq`` channels
from 100 MHz in 2 MHz steps.  The truth is a draw from an isotropic prior
``C_l = 100 K^2 / (1 + l)^2`` (also the prior used for inference), the noise a fixed
per-component sigma, 10% of the rms model visibility (constant in time and baseline,
so the noise is time-stationary): nothing depends on a sky model.

Response: ``gcrsky.instrument.response_matrix`` (ring-factored quadrature, beam floor
1e-16); nside 64 for lmax <= 50, 128 for lmax 100, 256 for lmax 200.  The response
column includes the autos' response.  ``auto`` is the path ``method="auto"`` picks
(:func:`gcrsky.solvers.plan_sampler`).

Sampler paths (``gcrsky.prepare`` + ``gcrsky.draw`` unless noted):

* ``chol``:  dense P + Cholesky;
* ``cgD-ny`` / ``cgD-mb``: CG on the dense P, Nystrom / m-block preconditioner;
* ``cgMF-ny``: matrix-free CG, Nystrom preconditioner;
* ``mmode``: ``gcrsky.solvers.mmode.prepare_mmode`` / ``draw_mmode`` (exact; needs uniform
  full-day coverage with Nt > 2 lmax and time-stationary noise, else 'n/a' with the
  reason ``mmode_check`` gives).

For each: compile time (``jit(...).lower(...).compile()``, AOT, so it never runs the
computation twice), set-up run time, time per draw (``ndraws`` draws in one call /
``ndraws``), and for CG the iterations of the Wiener solve (mean over channels) and the
mean iterations per draw.  ``it_noPC`` is plain CG (identity preconditioner,
``gcrsky.solvers.cg.pcg`` on the dense P of channel 0, started at 0 like the Wiener solve)
run until its residual ``||b - P x||`` reaches the relative residual the m-block CG
Wiener solve achieved (the same tolerance in residual terms), capped at 20000
('capped').  ``P_MB`` is the size of one dense P (all channels) where formed.
A path is skipped ('skip') when its estimated cost exceeds the per-configuration
budget (dense P: 8 Nf Nbl n^2 min(1, Nt/2) flops > 4e11 -- P by m-blocks since 2026-12-02, 8 Nf Nt Nbl n^2
by times before -- or P > 3 GB; matrix-free CG: the
matvecs for set-up + draws > ~6e11 flops); the reason is printed.

Measured (2026-11-22, this repository's machine: 2 shared x86 cores, 24 GB, CPU JAX float64,
gcrsky safe threading; load 2-4 from other jobs, so times are ~2x the quiet machine's),
default grid, 1226 s wall (the first two rows re-run after the Cholesky sampler started
drawing with a precomputed ``L^-T``).  Path cell: setup compile s + setup run s / time
per draw [CG iterations: Wiener, mean per draw]; resp_s includes the autos; prob_s =
simulate data + assemble the problem; ``auto`` is what ``method="auto"`` picks; skips are
explained in the run output (dense P or matrix-free CG over budget; mmode n/a when
coverage is not a uniform full day with Nt > 2 lmax).  it_noPC on the 24 h rows targets
the m-block solve's ~1e-16 relative residual (m-blocks are exact there), i.e. machine
precision: not meaningful ('nc': not reached).  ``ds`` (the exact data-space path,
``gcrsky.solvers.dataspace.prepare_dataspace`` / ``draw_dataspace``, added 2026-12-02) runs only
where ``N_d = 2 Nt Nbl < n``: in this grid only l50-a10-t10-8h-f1 (N_d = 900, n = 2601);
(a) measured 2026-12-02 in a separate run of that row (load ~5; the same run gave chol
2.5+3.3/2.92ms, cgMF-ny 4.8+0.5/61.3ms [35,33]); the other cells are 2026-11-22's.

::

    config               n      Nbl  resp_s  prob_s  P_MB    peak_MB  auto     it_noPC   chol                          cgD-ny                        cgD-mb                        cgMF-ny                       mmode                              ds (2026-12-02)
    l20-a10-t10-8h-f1    441    45      2.0     1.2  1.6     739      cholesky 909       1.9+0.3/0.153ms               3.0+0.9/2.03ms [1,1]          3.3+0.1/8.14ms [179,195]      3.3+2.5/2.86ms [1,1]          skip                          - (N_d >= n)
    l20-a10-t240-24h-f1  441    45      1.9     1.1  1.6     1089     mmode    2192(nc)  1.8+1.4/0.146ms               2.9+1.3/11ms [8,8]            2.2+1.7/8.55ms [2,1]          3.5+3.0/77.5ms [8,8]          1.4+0.0/0.126ms               - (N_d >= n)
    l20-a37-t10-8h-f1    441    666     3.3     1.5  1.6     808      cholesky 1716      4.5+1.4/0.327ms               8.4+1.8/4.34ms [2,2]          3.1+1.1/18.8ms [370,389]      6.0+3.2/29.3ms [2,2]          skip                          - (N_d >= n)
    l20-a37-t240-24h-f1  441    666     6.7     4.8  1.6     851      mmode    4883(nc)  6.7+33.1/0.169ms              8.2+20.6/41.4ms [26,23]       3.2+27.3/45ms [2,2]           skip                          4.0+0.3/0.36ms                - (N_d >= n)
    l20-a91-t10-8h-f1    441    4095    9.7     2.7  1.6     1039     cholesky 3013      3.8+6.3/0.284ms               6.3+5.8/17.2ms [2,2]          8.3+16.0/141ms [683,707]      13.7+5.7/140ms [2,2]          skip                          - (N_d >= n)
    l20-a91-t240-24h-f1  441    4095    7.8     3.5  1.6     930      mmode    n/a (no dense P) skip                          skip                          skip                          skip                          6.1+2.9/0.15ms                - (N_d >= n)
    l50-a10-t10-8h-f1    2601   45      4.3     2.1  54.1    962      cholesky 3039      5.0+5.5/6.4ms                 5.7+6.3/22.3ms [34,33]        2.0+2.8/394ms [400,441]       3.3+0.6/51.7ms [34,33]        skip                          2.5+0.3/2.68ms (a)
    l50-a10-t60-8h-f1    2601   45      3.6     1.8  54.1    1338     cholesky 6659      3.6+14.8/9.28ms               6.3+19.4/65.6ms [90,83]       2.6+11.7/729ms [658,738]      5.6+7.2/834ms [90,83]         skip                          - (N_d >= n)
    l50-a10-t240-24h-f1  2601   45      2.7     1.7  54.1    614      mmode    n/a (no dense P) skip                          skip                          skip                          skip                          1.8+0.1/0.802ms               - (N_d >= n)
    l50-a37-t10-8h-f1    2601   666     4.6     1.8  54.1    1115     cholesky 8031      2.3+25.0/7.95ms               6.3+25.5/71.1ms [114,105]     2.7+21.0/2.97e+03ms [1247,1336]  2.1+2.3/1.05e+03ms [110,103]  skip                          - (N_d >= n)
    l50-a37-t240-24h-f1  2601   666     5.5     1.7  54.1    978      mmode    n/a (no dense P) skip                          skip                          skip                          skip                          2.2+1.2/0.644ms               - (N_d >= n)
    l100-a37-t240-24h-f2 10201  666    30.4     4.9  1665.0  3307     mmode    n/a (no dense P) skip                          skip                          skip                          skip                          2.8+13.2/2.5ms                - (N_d >= n)
    l200-a37-t480-24h-f1 40401  666    80.7    13.1  13057.9 5351     mmode    n/a (no dense P) skip                          skip                          skip                          skip                          2.6+60.0/14.7ms               - (N_d >= n)

Headline (l100-a37-t240-24h-f2, ring response, m-mode path): response 30.4 s, set-up
13.2 s (+2.8 s compile), 200 draws 0.50 s, peak 3.3 GB (targets: < 5 min, < 5 min,
< 12 GB).  lmax 200 (37 antennas, 480 LSTs): response 81 s, set-up 60 s, 200 draws 2.95 s,
peak 5.4 GB.  Partial coverage at lmax 50 (8 h): no-preconditioner / m-block Wiener
iterations = 3039/400 (7.6x, 10 LSTs, 10 ants), 6659/658 (10.1x, 60 LSTs, 10 ants),
8031/1247 (6.4x, 10 LSTs, 37 ants); the prior-whitened Nystrom preconditioner needs
34 / 90 / 114 (89x, 74x, 70x).  Why m-blocks stop near 10x there: m-modes are global in
RA, 8 h of coverage is local, so the block diagonal credits the unobserved RA range
with the data's information; the m-block-preconditioned operator of the first case has
201 of 2601 eigenvalues below 0.1 (smallest 1.2e-3, i.e. ~1/SNR) -- grouping 2-8
consecutive m per block does not help (300-500 iterations).

Issue rows (``--hera``; HERA_GRID / HERA_SPEC).  Redundancy-compressed (name suffix
``-red``): one row per group of identical baselines (:func:`gcrsky.instrument.groups_for_array`;
37 antennas: 666 -> 63 groups, 331 antennas (hexagon of side 11, rows 11..21..11, 14.6 m):
54615 -> 630).  Where the full response fits (37 antennas) the system is gcrsky's exact
compression of the full problem (``redundant_responses`` -> ``build_problem`` ->
``compress_system``); for 331 antennas the full (Nf, 54615, n) response would be 79 GB
at lmax 300, so the compressed system is built directly from the unique rows
(``unique_response``) with ``W_g = N_g / sigma^2`` and data ``X_g a + noise`` of variance
``sigma^2 / N_g`` per component, which is what ``compress_visibilities`` gives (same
distribution; sigma as above, 10% of the rms |V| over all baselines).  nside 256 for
lmax 150-300.  resp_s: the unique rows (ring quadrature) plus their expansion to every
baseline where done.  Each path runs the number of draws of its spec: ``ds`` and
``mmode`` 200, matrix-free CG "a few" (3; 1 at 60 LSTs), so CG's per-draw time is
measured on those, in the same run as ``ds`` (ratios within one run).  CG tolerance:
``CGOptions()`` default, 1e-6 posterior sigma.  ``auto`` = ``plan_sampler``'s choice.

MEASURED 2026-12-02, 02:57-04:23 UTC, the same machine (2 shared cores, 23 GB), CPU JAX
float64.  The load average (1/5/15 min, at the start of each configuration) was 4-8 from
other jobs (test suites, other benchmarks) on the 2 cores, so every time here is ~2-4x
the quiet machine's.  Rows 1, 2 and 4 from one ``--hera`` run; row 3 re-run with
``--only`` after the first attempt (default D chunking, 2 CG draws) exceeded its 1200 s
limit; row 5 with ``--only`` (see below)::

    config                      n      Nbl/all      N_d     resp_s  prob_s  peak_MB  load(1/5/15) auto      ds                        cgMF-ny                        mmode
    l150-a37-t10-8h-f1-red      22801  63/666       1260      11.8     4.5  2190     3.7/3.0/2.7  dataspace 4.2+7.7/24ms              6.9+30.6/2.3e+04ms [583,555]   -
    l200-a37-t10-8h-f1-red      40401  63/666       1260      11.4     6.3  3197     7.3/4.7/3.4  dataspace 5.1+24.3/111ms            7.5+39.9/2.42e+04ms [361,333]  -
    l200-a37-t60-8h-f1-red      40401  63/666       7560       5.6     4.9  14879    4.9/5.0/5.6  dataspace 1.7+64.3/250ms (b)        2.6+253.6/2e+05ms [1481,1416]  -
    l300-a331-t601-24h-f1-red   90601  630/54615    757260   177.4     9.0  10632    4.1/5.8/6.1  mmode     skip (N_d > n)            -                              0.9+39.7/12.9ms
    l150-a331-t30-8h-f1-red     22801  630/54615    37800     28.6     1.5  4073     2.3/4.4/4.8  cg        skip (N_d > n)            2.8+1121.4 [5000]! (c)         -

(b) with ``DataSpaceOptions(time_chunk=20)``; the default chunking (``CHUNK_BYTES`` =
64 MiB of rows: 1 time per chunk here, 1830 block pairs of 126 x 126) took 2.1+285.3 s
for the same set-up in the same run (load 2-5): 4.4x slower.  All ``ds`` Wiener filters
have a true residual <= 4e-10 posterior sigma; the m-mode one 1.8e-7 sigma (err_sigma).

(A) Partial coverage, 37 antennas, 8 h, lmax 200 (MEASURED):

* 10 LSTs (N_d = 1260): response 11.4 s; data-space set-up 24.3 s (+5.1 s compile),
  200 exact draws 22.3 s (+4.4 s compile): set-up + 200 draws = 56.0 s with compile,
  46.6 s without -- goal (< 60 s) MET, under load ~7.  Matrix-free CG (Nystrom) in the same
  run: set-up 39.9 s (+7.5 s), 361 Wiener iterations, 333 per draw, 24.2 s per draw:
  217x the data-space draw.
* 60 LSTs (N_d = 7560): set-up 64.3 s (time_chunk 20; 285 s with the default chunking),
  200 draws 50.0 s: 117.5 s with compile -- goal NOT met (2x over).  CG: 1481 Wiener
  iterations, 1416 per draw, 200 s per draw (802x the data-space draw).
* The motivating case, lmax 150, 10 LSTs (issue: prepare 22 s, 139 CG iterations,
  6 s/draw on its own noise level): here CG needs 583 / 555 iterations (this benchmark's
  noise, 10% of the rms visibility, is a higher SNR), set-up 30.6 s, 23 s per draw;
  data space: set-up 7.7 s (+4.2 s compile), 24 ms per draw (959x faster per draw),
  set-up + 200 draws 20.2 s with compile.
* Where the time goes: at 10 LSTs half of it is the 200 draws (111 ms each at lmax 200:
  one matrix-free X and X^T product per draw, ``16 Nt Nbl n`` = 4e8 flop, i.e. the
  per-time rotations, not flops, dominate) and the other half D (1260^2 x 40401 = 6e10
  flop) plus the Wiener filter and its residual check (matrix-free P products).  At 60
  LSTs D (2.3e12 flop: 64 s = ~36 Gflop/s with 20-time chunks) and the draws (250 ms
  each) dominate.  Next bottleneck: the draws' matrix-free products (forming Y once,
  ``N_d x n`` = 0.4 GB at 10 LSTs / 2.4 GB at 60, would make 200 draws two GEMMs) and D's
  default chunk size (64 MiB is 1 time per chunk at lmax 200: raise it or chunk by rows).

(A') The same rows after two changes the measurements above pointed to (MEASURED
2026-12-02 04:31-04:34 UTC, load ~2, ``SCALE_PATHS=ds python benchmarks/scale.py --only
l150-a37-t10-8h-f1-red l200-a37-t10-8h-f1-red l200-a37-t60-8h-f1-red``): D built by the
stationary shortcut (one 126 x 126 block per distinct lag, 2 Nt - 1 of them, instead of
one per pair of times: ``gcrsky.solvers.dataspace.lag_structure``) and ``Y = W^1/2 X``
kept for the draws where it takes <= 4 GiB (``DataSpaceOptions.materialize``), so 200
draws are two matrix products::

    config                      n      Nbl/all      N_d     resp_s  prob_s  peak_MB  auto      ds
    l150-a37-t10-8h-f1-red      22801  63/666       1260       4.9     -     -        dataspace set-up + 200 draws 8.0 s (3.1 s without compile)
    l200-a37-t10-8h-f1-red      40401  63/666       1260       4.8     3.6  1982     dataspace 1.0+2.2/4.38ms
    l200-a37-t60-8h-f1-red      40401  63/666       7560       4.3     2.8  7712     dataspace 1.0+23.7/38.4ms

* lmax 200, 10 LSTs: set-up + 200 draws 5.6 s with compile (3.1 s run): goal (< 60 s) MET,
  10x under it; 200 draws 0.88 s (was 22.3 s).
* lmax 200, 60 LSTs: set-up 23.7 s (D by lags, its Cholesky factor 7560^3 / 3 = 1.4e11
  flop, Y 2.4 GB, the Wiener filter), 200 draws 7.7 s: 33.9 s with compile: goal MET (was
  117.5 s); peak 7.7 GB (was 14.9 GB: the per-draw rotated copies are gone).
* The set-up now goes mostly to forming Y (60 per-time responses at lmax 200) and the
  factorisation; the draws to the two GEMMs with Y (4 N_d n flop each).

(B) HERA core, full day, lmax 300 (l300-a331-t601-24h-f1-red; 601 LSTs over 24 h, endpoint
excluded; MEASURED except where marked): response (630 unique rows, ring quadrature)
177.4 s + system assembly 9.0 s + m-mode set-up 39.7 s (+0.9 s compile) = 227 s
(goal < 20 min: MET); 200 draws 2.57 s (+2.0 s compile; goal < 1 min: MET); peak RSS
10.6 GB (goal < 16 GB: MET), at load 4-6.  Rings vs healpy SHT on the first 32 unique
rows, same process: rings 5.6 s (incl. ~3 s JIT compile), SHT 2.1 s; max |R_rings -
R_sht| / max |R| = 3.3e-14, worst row ||dR|| / ||R|| = 8.5e-13 (< 1e-12: agree).
EXTRAPOLATED linearly in Nbl to all 630 rows: SHT ~41 s against 177.4 s MEASURED for the
rings (whose 32-row time, 5.6 s, extrapolates to only ~109 s: the full build scales
worse than linearly).  The SHT route is ~4x faster here.  Where the time goes: the
response (78% of the 227 s), then the m-mode set-up (block build ``O(Nbl lmax^3)``:
630 x 301^3 x 3 Gram products, 301 Cholesky factors of 602 x 602, and the matrix-free
Wiener right-hand side / residual over 601 times).  Next bottleneck: with the SHT
response (~41 s) the m-mode set-up; then memory: the peak (10.6 GB for one channel: the
unique response 0.9 GB, its gathered (Nbl, M, 2M) m-layout copies ~1.8 GB each, Gram
intermediates, the (Nt, n) rotated copies of the matrix-free products) grows linearly
in Nf, so more than one channel at lmax 300 needs a per-channel loop.

(C) 331 antennas, 8 h, 30 LSTs, lmax 150 (l150-a331-t30-8h-f1-red, MEASURED, ``--only`` with
a 1380 s limit, load 2-7): (c) matrix-free CG with the Nystrom preconditioner (rank 128)
did NOT reach 1e-6 sigma: it stopped at ``maxiter`` = 5000 (the ``CGOptions`` default)
after 1121 s (0.22 s per iteration; one product ``16 Nt Nbl n`` = 6.9e9 flop) with the
error still 5.3e-2 posterior sigma ('!').  The m-block preconditioner was not reached in
that run; a separate run of it alone (``SCALE_PATHS=cgMF-mb``, 620 s limit, load 5-7) did
not finish its set-up + Wiener solve in ~590 s, i.e. (at ~0.22 s per product) it needs
more than ~2500 iterations: its iteration count is NOT measured.  Data space: N_d = 2 x 30 x 630 = 37800 > n =
22801, so it is not the cheaper side (skipped); ESTIMATED: D 11.4 GB
(``dataspace_memory_bytes`` ~46 GB with its factor and transient copies: does not fit in
23 GB), D ~3.3e13 flop (~15 min at the ~36 Gflop/s row 3 reached) plus its Cholesky
~1.8e13 flop.  The dense primal P (n = 22801: 4.2 GB, ~12.5 GB with factor and L^-T)
would fit but costs ``8 Nt Nbl n^2`` ~7.9e13 flop (~40 min, ESTIMATED).  This case has
no cheap exact path today.  Measured goal set for it: an exact solve to 1e-6 sigma in < 5 min
on this machine.  The next step toward it is structural: every matrix-free product costs
``O(Nt Nbl n)`` because each time rotates the whole coefficient vector, but a rotation
about the pole is a phase per m, so ``X a`` factorises into per-m sums over l (``O(Nbl n)``
once) and a short Fourier sum over m per time (``O(Nt Nbl lmax)``): ~Nt x cheaper CG
iterations here (30 LSTs), and the same for the dense P build.  Not done in this round.

(C') The same row after building P by m-blocks (MEASURED 2026-12-02 07:05-07:09 UTC, load
~2, ``SCALE_PATHS=chol python benchmarks/scale.py --only l150-a331-t30-8h-f1-red``).  A
rotation about the pole is a phase per m, so ``X^T W X`` is one real product over
``4 Nbl`` per order m (``gcrsky.model.system.precision_data_matrix``): ~8 Nbl n^2 = 2.6e12 flop
whatever Nt (1.25x that with the loops' fixed windows), against 4 Nt Nbl n^2 = 3.9e13
summed over times.  Exact dense Cholesky (``method="auto"`` picks it)::

    config                      n      Nbl/all    N_d    resp_s  prob_s  peak_MB  auto      chol
    l150-a331-t30-8h-f1-red     22801  630/54615  37800    29.7     2.1  13283    cholesky  205 (incl. compile) / 28.5ms

* set-up 204.9 s (P by m-blocks ~94 s and its factor ~127 s on one OpenBLAS thread, the
  times of a separate run; the Wiener filter by the factor), 200 draws 5.7 s (two
  triangular solves per batch: above n = 12000 no ``L^-T`` is formed), Wiener filter
  error 3.3e-8 posterior sigma; the whole configuration 250 s wall with the response.
  Goal (exact to 1e-6 sigma in < 5 min): MET.
* Peak 13.3 GB: the set-up runs as two programs (P, then its factor).  Under one outer
  ``jit`` they fuse and peaked at 21.0 GB (an earlier run of this row: P being built,
  LAPACK's copy and the factor at once).
* The threaded OpenBLAS ``dpotrf`` crashes at this size (segfault from n = 16000 on this
  host); ``use_safe_cpu_threading``'s ``OPENBLAS_NUM_THREADS=1`` avoids it, and
  ``prepare_cholesky`` refuses n > 14000 without it.
* Where the time goes now: the factor (n^3 / 3 = 4e12 flop) and P (2.6e12); next
  bottleneck is memory (P and its factor, 8.3 GB, grow as lmax^4), so lmax >~ 160 needs the
  matrix-free route, whose products still cost ``O(Nt Nbl n)`` each.

(C'') The same row with the dense factor on the host (MEASURED 2026-12-03 20:27-20:29 UTC, load ~1-2,
``SCALE_PATHS=chol python benchmarks/scale.py --only l150-a331-t30-8h-f1-red`` under ``/usr/bin/time -v``).
``prepare_cholesky`` without ``L^-T`` (n > 12000) now factorises P with ``gcrsky.solvers.blocked.blocked_cholesky``
on every core (threadpoolctl; ``potrf`` only on 1024-wide panels) instead of XLA's one-threaded factor::

    config                      n      Nbl/all    N_d    resp_s  prob_s  peak_MB  auto      chol
    l150-a331-t30-8h-f1-red     22801  630/54615  37800     5.5     2.0  13413    cholesky  138.0 (incl. compile) / 20.3ms

* set-up 204.9 -> 138.0 s (1.49x), 200 draws 4.1 s (1.4 s of it compilation), Wiener filter error 3.0e-8
  posterior sigma; the whole configuration 157.4 s wall with the response (was 250 s: issue 24 item 2's
  "the lmax 150 row faster than today's 250 s": met, 1.59x); process peak 13.7 GB (``/usr/bin/time``),
  13.4 GB by the script (was 13.3).

(B') Response routes side by side, all 630 unique rows of the 331-antenna hexagon, nside
256, 1 channel (MEASURED 2026-12-02 06:53-07:06 UTC, load 0.4-2, one process per lmax,
``python benchmarks/response_routes.py 300 256 331`` and ``150 256 331``): lmax 300: rings 115.6 s, SHT 41.5 s (2.8x), max |dR| / max |R| =
3.3e-14; lmax 150: rings 27.0 s, SHT 24.6 s (1.1x), 2.3e-14.  Row by row the two agree to
9.2e-9 of the row's norm over the rows with norm > 1e-6 of the largest; the worst rows
(norm 6e-14 of the largest: fringes far beyond lmax) differ at the level of the
rings' beam-floor cut.  ``response_matrix(method="auto")`` (the default) now builds by
the SHT from lmax 200 (``RESPONSE_SHT_MIN_LMAX``).  The 177 s of (B) was the rings under
load 4-6 inside the full m-mode run; the SHT route there is MEASURED 41.5 s here.

(D) Issue 24 item 2: 331 antennas, 8 h, 30 LSTs, lmax 300 (l300-a331-t30-8h-f1-red, MEASURED 2026-12-03
06:56-07:10 UTC, ``python benchmarks/scale.py --only l300-a331-t30-8h-f1-red``; load 1.0 at the start,
5-6 later: the test suite of a fresh clone ran alongside).  n = 90601 (a dense P: 66 GB), N_d = 37800
(D: 11.4 GB, D + factor + transients of the standard set-up: 46 GB)::

    config                      n      Nbl/all    N_d    resp_s  prob_s  peak_MB  ds (in place)              cgMF-ny (maxiter 300)
    l300-a331-t30-8h-f1-red     90601  630/54615  37800    10.8     3.1  13846    470.2 / 131 ms per draw     13.6+300.1 [300]! err 1.6e+05 sigma

* The in-place data space (``gcrsky.solvers.dataspace_large``): lag blocks from per-order Grams, D filled
  and factorised in its own host buffer (N_d^3 / 3 = 1.8e13 flop, one OpenBLAS thread), the Wiener filter
  through the host factor: set-up 470 s, 200 draws 26.2 s (+4.6 s compile): set-up + 200 draws 501 s
  (goal < 30 min: met); the set-up's peak 13.8 GB (goal < 16 GB: met; its estimate, beyond the system,
  14.2 GB with 200 draws); Wiener filter exact to 2.4e-8 posterior sigma (goal 1e-6: met).  Every draw
  exact (Hoffman-Ribak through the factor): no iteration count.
* Matrix-free CG, prior-whitened Nystrom (rank 128), m-factorised products (1.0 s per iteration): after
  300 iterations the rigorous error bound is still 1.6e5 posterior sigma.  The block-banded window
  preconditioner does not change that at 8 h (``benchmarks/window_pc.py``: at lmax 64 it needs 1060
  iterations against Nystrom's 786; it pays only for coverage of most of the day), so the ``<= 200 CG
  iterations`` route of the issue is not what makes this case exact: the data space is.
* The process's peak over the whole row, 15.8 GB, is the CG run after the data space (its Nystrom sketch
  and work vectors on top of the response).
* Where the time goes: the factorisation (~75 % of the set-up), D's fill and the lag blocks (1.2e12 flop of
  per-order Grams instead of 1.7e13 lag by lag), the Wiener filter's three products.  Next bottleneck:
  the factorisation runs on one core (``OPENBLAS_NUM_THREADS=1``, which the threaded ``dpotrf`` crash
  above N = 14000 imposes; the blocked factorisation calls only ``dpotrf`` on 1024-wide blocks, so its
  GEMMs could take both cores).
* Done 2026-12-03 afternoon: ``blocked_cholesky`` raises the BLAS threads for its own call (threadpoolctl; the
  cores, or ``GCRSKY_BLAS_THREADS``).  MEASURED 14:28-14:34 UTC, the ``ds`` column alone (a script that sets
  ``HERA_SPEC[...]["paths"] = ["ds"]`` and calls ``run_one``; load 0.5 at the start, ~2 at the set-up's end:
  a 1-minute test run shared the cores): set-up 470.2 -> 297.5 s (1.58x), 200 draws 15.1 s (76 ms a draw;
  the 131 ms above was under load 5-6), set-up + 200 draws 313 s; Wiener filter 2.4e-8 posterior sigma;
  the set-up's peak 13.86 GB (MiB: 13857) as before, the process's peak over the row 15.8 GiB (15839 MiB,
  ``/usr/bin/time``: 16.2 GB): without the CG column, so the draws' phase holds ~2 GB above the set-up
  (where exactly: not profiled).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

ROWS = {10: (3, 4, 3), 37: (4, 5, 6, 7, 6, 5, 4), 91: (6, 7, 8, 9, 10, 11, 10, 9, 8, 7, 6),
        331: tuple(range(11, 21)) + (21,) + tuple(range(20, 10, -1))}  # 331: HERA core, side 11

# (lmax, nants, nlst, hours, nfreq, ndraws)
DEFAULT_GRID = [
    (20, 10, 10, 8, 1, 20),
    (20, 10, 240, 24, 1, 20),
    (20, 37, 10, 8, 1, 20),
    (20, 37, 240, 24, 1, 20),
    (20, 91, 10, 8, 1, 20),
    (20, 91, 240, 24, 1, 20),
    (50, 10, 10, 8, 1, 20),
    (50, 10, 60, 8, 1, 20),  # target (b): partial coverage at lmax 50
    (50, 10, 240, 24, 1, 20),
    (50, 37, 10, 8, 1, 20),
    (50, 37, 240, 24, 1, 20),
    (100, 37, 240, 24, 2, 200),  # the headline
    (200, 37, 480, 24, 1, 200),  # lmax 200 "if it fits"
]
QUICK_GRID = [(20, 10, 10, 8, 1, 5), (20, 10, 48, 24, 1, 5)]

# The issue rows (``--hera``): redundancy-compressed (name suffix ``-red``), each with the
# paths it measures.  spec keys: paths (run as ds, then CG, then mmode; no flop budget),
# ndraws per path (CG: "a few"; 0: Wiener solve only), cg_tol (None: CGOptions' default), cg_maxiter,
# ds_chunks (DataSpaceOptions.time_chunk of the timed set-up + draws, then set-up only for
# the others), resp_compare (unique rows for the rings vs SHT check), nd_estimate_only
# (report D's size / cost, do not build it), timeout (s, per configuration).
HERA_GRID = [
    (150, 37, 10, 8, 1, 200),  # the motivating case (was: prepare 22 s, 139 CG its, 6 s/draw)
    (200, 37, 10, 8, 1, 200),  # (A) partial coverage, lmax 200
    (200, 37, 60, 8, 1, 200),
    (300, 331, 601, 24, 1, 200),  # (B) HERA core, full day, lmax 300, m-mode
    (150, 331, 30, 8, 1, 0),  # (C) HERA core, 8 h: CG iterations per preconditioner
    (300, 331, 30, 8, 1, 200),  # (D) issue 24 item 2: HERA core, 8 h, lmax 300 (in-place data space)
    (650, 331, 1301, 24, 1, 200),  # (E) issue 24 item 1: HERA core, full day, lmax 650 (bucketed m-mode)
]
HERA_SPEC = {
    "l150-a37-t10-8h-f1-red": dict(paths=["ds", "cgMF-ny"], ndraws={"ds": 200, "cgMF-ny": 3}, timeout=900),
    "l200-a37-t10-8h-f1-red": dict(paths=["ds", "cgMF-ny"], ndraws={"ds": 200, "cgMF-ny": 3}, timeout=900),
    "l200-a37-t60-8h-f1-red": dict(paths=["ds", "cgMF-ny"], ndraws={"ds": 200, "cgMF-ny": 1}, ds_chunks=[None],
                                   timeout=1200),
    "l300-a331-t601-24h-f1-red": dict(paths=["mmode"], ndraws={"mmode": 200}, resp_compare=32, timeout=1200),
    "l150-a331-t30-8h-f1-red": dict(paths=["chol", "cgD-mb", "cgD-ny", "cgMF-ny", "cgMF-mb"],
                                    ndraws={"chol": 200, "cgD-mb": 0, "cgD-ny": 0, "cgMF-ny": 0, "cgMF-mb": 0},
                                    cg_tol=1e-6, nd_estimate_only=True, timeout=1500),
    "l650-a331-t1301-24h-f1-red": dict(paths=["mmode"], ndraws={"mmode": 200}, timeout=2400),
    "l300-a331-t30-8h-f1-red": dict(paths=["ds", "cgMF-ny"], ndraws={"ds": 200, "cgMF-ny": 0}, cg_tol=1e-6,
                                    cg_maxiter=300, timeout=2400),
}

DENSE_FLOP_MAX = 4e11
DENSE_BYTES_MAX = 3e9
MF_FLOP_MAX = 6e11
NOPC_CAP = 20000


def name_of(c) -> str:
    lmax, na, nt, h, nf, nd = c[:6]
    red = len(c) > 6 and c[6]
    return f"l{lmax}-a{na}-t{nt}-{h}h-f{nf}" + ("-red" if red else "")


def _red(grid):
    return [tuple(c) + (True,) for c in grid]


def parse_name(s: str, grid):
    for c in grid + DEFAULT_GRID + QUICK_GRID + _red(HERA_GRID):
        if name_of(c) == s:
            return c
    parts = s.split("-")
    red = parts[-1] == "red"
    lm, a, t, h, f = parts[:5]
    lmax = int(lm[1:])
    c = (lmax, int(a[1:]), int(t[1:]), int(h[:-1]), int(f[1:]), 200 if lmax >= 100 else 20)
    return c + (True,) if red else c


def spec_of(c) -> dict:
    """The measurement spec of a configuration: the default grid's (every path within budget), or HERA_SPEC's."""
    nm = name_of(c)
    if nm in HERA_SPEC:
        spec = dict(HERA_SPEC[nm])
        if os.environ.get("SCALE_PATHS"):  # e.g. SCALE_PATHS=cgMF-mb: run only these paths of the row
            spec["paths"] = os.environ["SCALE_PATHS"].split(",")
        return spec
    if len(c) > 6 and c[6]:  # an ad-hoc compressed row: data space where it applies, CG, m-mode
        return dict(paths=["ds", "cgMF-ny", "mmode"], ndraws={"cgMF-ny": 3})
    return {}


def load_now() -> str:
    return "%.1f/%.1f/%.1f" % os.getloadavg()


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KB


# ---------------------------------------------------------------- one configuration


def partial(out) -> None:
    """Print the results so far (the driver keeps the last such line if the configuration times out)."""
    print("PARTIAL:" + json.dumps(dict(out, peak_MB=peak_mb(), load_end=load_now())), flush=True)


def run_one(c) -> dict:
    from gcrsky.parallel import use_safe_cpu_threading

    use_safe_cpu_threading()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import gcrsky
    from gcrsky.base.memory import available_memory_bytes
    from gcrsky.inference import draw, prepare_system
    from gcrsky.instrument import (
        HERA_LATITUDE_DEG,
        antpairs,
        gaussian_beam,
        groups_for_array,
        hex_array,
        make_array,
        redundant_responses,
        response_matrix,
    )
    from gcrsky.model import LinearSystem, VisOperator, apply, build_problem, compress_system, isotropic_prior
    from gcrsky.solvers import CGOptions, DataSpaceOptions, mmode_check, plan_sampler
    from gcrsky.solvers.cg import pcg
    from gcrsky.solvers.dataspace import (
        _prepare_dataspace,
        dataspace_memory_bytes,
        draw_dataspace,
        lag_structure,
        materialize_rows,
        prepare_dataspace,
        use_in_place,
    )
    from gcrsky.solvers.dense import CHOLESKY_INVERSE_MAX_N
    from gcrsky.solvers.mmode import draw_mmode, prepare_mmode
    from gcrsky.sphere import n_params

    lmax, nants, nt, hours, nf, ndraws = c[:6]
    red = len(c) > 6 and bool(c[6])
    spec = spec_of(c)
    out = {"name": name_of(c), "lmax": lmax, "nants": nants, "nlst": nt, "hours": hours, "nfreq": nf,
           "ndraws": ndraws, "paths": {}, "notes": [], "red": red, "load_start": load_now()}
    nside = 64 if lmax <= 50 else (128 if lmax <= 100 else (256 if lmax <= 300 else 512))
    n = n_params(lmax)
    nbl_all = nants * (nants - 1) // 2
    out.update(n=n, nside=nside, nbl_all=nbl_all)
    freqs = 100e6 + 2e6 * np.arange(nf)
    arr = make_array(hex_array(ROWS[nants], 14.6), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    pairs = antpairs(nants)
    autop = np.stack([np.arange(nants)] * 2, 1)
    if hours >= 24:
        lsts = np.arange(nt) * (2 * np.pi / nt)
    else:
        lsts = np.linspace(0.0, hours * 2 * np.pi / 24.0, nt)
    ell = np.arange(lmax + 1)
    cl = np.tile(100.0 / (1.0 + ell) ** 2, (nf, 1))
    prior = isotropic_prior(cl, n)
    std = 1.0 / np.sqrt(np.asarray(prior.inv_var))
    a_true = std * np.random.default_rng(1).standard_normal((nf, n))

    def sigma_of(R, weights=None):  # 10% of the rms |V| under the prior (over all baselines)
        p = np.einsum("fbk,fk->fb", np.abs(np.asarray(R)) ** 2, std**2)
        vrms = np.sqrt(np.average(p, axis=1, weights=weights).mean())
        return 0.1 * vrms / np.sqrt(2.0)

    if not red:
        nbl = nbl_all
        t0 = time.perf_counter()
        out["response"] = "rings"
        resp = response_matrix(arr, pairs, freqs, lmax, nside).block_until_ready()
        auto = response_matrix(arr, autop, freqs, lmax, nside).block_until_ready()
        out["t_response"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        sigma = sigma_of(resp)
        prob = build_problem(arr, freqs, lsts, lmax, nside, a_true=a_true, sigma=sigma, prior=prior,
                             responses=(resp, auto), key=jax.random.PRNGKey(3))
        system = prob.system()
        del resp, auto, prob
    else:
        # Redundancy-compressed: one row per group of identical baselines (exact; gcrsky.model.compress).
        t0 = time.perf_counter()
        groups = groups_for_array(arr)
        out["t_groups"] = time.perf_counter() - t0
        nbl = groups.n_groups
        cmp_n = spec.get("resp_compare")
        if cmp_n:  # rings vs healpy-SHT route on the first cmp_n unique rows, same process, both timed
            from gcrsky.instrument.response_sht import response_matrix_sht

            reps = groups.representative_antpairs[:cmp_n]
            t0 = time.perf_counter()
            Rr = np.asarray(response_matrix(arr, reps, freqs, lmax, nside))
            t_r = time.perf_counter() - t0
            t0 = time.perf_counter()
            Rs = np.asarray(response_matrix_sht(arr, reps, freqs, lmax, nside))
            t_s = time.perf_counter() - t0
            rel = float(np.max(np.abs(Rr - Rs)) / np.max(np.abs(Rr)))
            rowrel = float(np.max(np.linalg.norm(Rr - Rs, axis=-1) / np.linalg.norm(Rr, axis=-1)))
            out["resp_compare"] = dict(nbl=len(reps), t_rings=t_r, t_sht=t_s, rel_max=rel, rel_row=rowrel,
                                       load=load_now())
            partial(out)
            del Rr, Rs
        t0 = time.perf_counter()
        out["response"] = "rings, unique rows"
        if nbl_all * n * 16.0 * nf <= 2e9:
            # small enough for the full (gathered) response: gcrsky's own compression of the full problem
            resp, auto = redundant_responses(arr, groups, freqs, lmax, nside)
            jax.block_until_ready((resp, auto))
            out["t_response"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            sigma = sigma_of(resp)
            prob = build_problem(arr, freqs, lsts, lmax, nside, a_true=a_true, sigma=sigma, prior=prior,
                                 responses=(resp, auto), key=jax.random.PRNGKey(3))
            system = compress_system(prob.system(), groups)
            out["compression"] = "build_problem (all baselines) + compress_system"
            del resp, auto, prob
        else:
            # the full response (Nbl_all rows) would not fit: build the compressed system directly from
            # the unique rows: W_g = N_g / sigma^2 (what compress_visibilities gives), d_g = X_g a + noise
            # of per-component variance sigma^2 / N_g (the distribution of the compressed data)
            from gcrsky.instrument import unique_response

            R_u = unique_response(arr, groups, freqs, lmax, nside).block_until_ready()
            out["t_response"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            counts = np.asarray(groups.counts, np.float64)
            sigma = sigma_of(R_u, weights=counts)
            op = VisOperator(R_u, jnp.asarray(lsts))
            V = apply(op, jnp.asarray(a_true))
            k1, k2 = jax.random.split(jax.random.PRNGKey(3))
            sg = jnp.asarray(sigma / np.sqrt(counts))
            noise = sg * (jax.random.normal(k1, V.shape) + 1j * jax.random.normal(k2, V.shape))
            iv = jnp.broadcast_to(jnp.asarray(counts / sigma**2), V.shape)
            system = LinearSystem(op, V + noise, iv, prior._replace(mean=jnp.asarray(prior.mean),
                                                                    inv_var=jnp.asarray(prior.inv_var)))
            out["compression"] = "compressed system built from the unique rows (full response would not fit)"
            del V, noise
    jax.block_until_ready(system.data)
    out["t_problem"] = time.perf_counter() - t0
    out["nbl"] = nbl
    nd = 2 * nt * nbl
    out["N_d"] = nd
    out["auto"] = plan_sampler(system, ndraws=ndraws).method
    key = jax.random.PRNGKey(7)
    partial(out)

    jit_prepare = jax.jit(prepare_system, static_argnames=("method", "options", "tol"))
    jit_draw = jax.jit(draw, static_argnames=("ndraws",))

    def timed(jitted, args, static, dyn_kw=None):
        """AOT compile (timed), then one timed run."""
        dyn_kw = dyn_kw or {}
        t0 = time.perf_counter()
        comp = jitted.lower(*args, **static, **dyn_kw).compile()
        tc = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = jax.block_until_ready(comp(*args, **dyn_kw))
        return res, tc, time.perf_counter() - t0

    dense_flops = 8.0 * nf * min(1.0, nt / 2.0) * nbl * n * n  # P by m-blocks (was 8 Nf Nt Nbl n^2 by times)
    dense_bytes = 8.0 * nf * n * n
    mv_flops = 16.0 * nf * nt * nbl * n
    dense_ok = dense_flops <= DENSE_FLOP_MAX and dense_bytes <= DENSE_BYTES_MAX
    dense_why = (f"dense P ~{dense_flops:.1e} flop, {dense_bytes / 1e9:.2f} GB "
                 f"(limits {DENSE_FLOP_MAX:.0e} flop, {DENSE_BYTES_MAX / 1e9:.0f} GB)")
    out["P_MB"] = dense_bytes / 1e6
    out["D_MB"] = 8.0 * nf * nd * nd / 1e6
    cg_tol = spec.get("cg_tol")
    ndr = spec.get("ndraws", {})

    all_paths = {"chol": dict(method="cholesky"),
                 "cgD-ny": dict(options=CGOptions(dense=True, preconditioner="nystrom")),
                 "cgD-mb": dict(options=CGOptions(dense=True, preconditioner="mblock")),
                 "cgMF-ny": dict(options=CGOptions(dense=False, preconditioner="nystrom")),
                 "cgMF-mb": dict(options=CGOptions(dense=False, preconditioner="mblock"))}
    if cg_tol is not None:
        for k in ("cgD-ny", "cgD-mb", "cgMF-ny", "cgMF-mb"):
            o = all_paths[k]["options"]
            all_paths[k] = dict(options=CGOptions(dense=o.dense, preconditioner=o.preconditioner, tol=cg_tol,
                                                  maxiter=spec.get("cg_maxiter", CGOptions.maxiter)))
    wanted = spec.get("paths", ["chol", "cgD-ny", "cgD-mb", "cgMF-ny", "mmode", "ds"])
    # data space: exact, through the N_d x N_d matrix D = I + W^1/2 X S X^T W^1/2 (only where N_d < n)
    if "ds" in wanted or spec.get("nd_estimate_only"):
        flop_D = nf * float(nd) ** 2 * n  # symmetric half of the 2 N_d^2 n block products
        flop_chol = nf * float(nd) ** 3 / 3
        out["ds_estimate"] = dict(N_d=nd, D_GB=8.0 * nf * nd * nd / 1e9, flop_D=flop_D, flop_chol=flop_chol,
                                  mem_GB=dataspace_memory_bytes(system, 1) / 1e9)
        if nd >= n:
            out["paths"]["ds"] = {"skip": f"N_d = {nd} >= n = {n}: data space is not the cheaper side"}
        elif spec.get("nd_estimate_only"):
            out["paths"]["ds"] = {"skip": "estimate only"}
        else:
            nd_p = int(ndr.get("ds", ndraws))
            rec = {"load": load_now(), "ndraws": nd_p}
            chunks = spec.get("ds_chunks", [None])
            t0 = time.perf_counter()
            lags = lag_structure(system)  # the stationary shortcut, as prepare_dataspace takes it (None: general)
            t_lags = time.perf_counter() - t0
            dso = DataSpaceOptions(time_chunk=chunks[0])
            in_place = use_in_place(system, dso, lags, available_memory_bytes())
            if in_place:  # host-orchestrated (not one jit): time it as a user calls it, compile included
                t0 = time.perf_counter()
                prep = jax.block_until_ready(prepare_dataspace(system, dso))
                tc, tr, mat = 0.0, time.perf_counter() - t0, False
                rec["setup_note"] = "in place (gcrsky.solvers.dataspace_large): compile included in the set-up time"
            else:
                mat = materialize_rows(system, dso)  # as prepare_dataspace decides it
                prep, tc, tr = timed(_prepare_dataspace, (system,), dict(options=dso, materialize=mat),
                                     dict(lags=lags))
            tr += t_lags
            rec.update(setup_compile=tc, setup=tr, time_chunk=str(chunks[0]), load_setup_end=load_now(),
                       stationary=lags is not None, n_lags=None if lags is None else int(lags.lags.shape[0]),
                       materialized=mat, in_place=in_place, peak_MB_setup=peak_mb())
            out["paths"]["ds"] = rec
            partial(out)
            (dr, info), tc2, tr2 = timed(draw_dataspace, (key, prep), dict(ndraws=nd_p))
            rec.update(draw_compile=tc2, draw_total=tr2, per_draw=tr2 / nd_p)
            rec["ok"] = bool(np.all(np.asarray(info.draws.converged)) and np.all(np.asarray(prep.wiener.converged)))
            rec["wiener_err_sigma"] = float(np.max(np.asarray(prep.wiener.err_sigma)))
            out["paths"]["ds"] = rec
            del prep, dr, info
            partial(out)
            for ch in chunks[1:]:  # alternative time chunks of D's assembly: set-up only
                pr, tc, tr = timed(_prepare_dataspace, (system,), dict(options=DataSpaceOptions(time_chunk=ch)))
                rec.setdefault("setup_by_chunk", {})[str(ch)] = [tc, tr, load_now()]
                del pr
                out["paths"]["ds"] = rec
                partial(out)
    rel_mb = None
    for pname in [p for p in wanted if p in all_paths]:
        static = all_paths[pname]
        nd_p = int(ndr.get(pname, ndraws))
        rec = {"load": load_now(), "ndraws": nd_p}
        if static.get("method") == "cholesky" or static["options"].dense:
            if not dense_ok and not spec:  # an issue row runs the paths it names
                out["paths"][pname] = {"skip": dense_why}
                continue
        elif not spec:  # default grid: budget the matrix-free CG
            est = mv_flops * (128 + 2 * 40 + nd_p * 2 * 40)
            if est > MF_FLOP_MAX:
                out["paths"][pname] = {"skip": f"matrix-free CG ~{est:.1e} flop (~{mv_flops:.1e}/matvec) > {MF_FLOP_MAX:.0e}"}
                continue
        if static.get("method") == "cholesky" and n > CHOLESKY_INVERSE_MAX_N:
            # the large-n Cholesky set-up is two programs (P, then its factor); under one outer jit
            # they would fuse and hold 5.25 n^2 doubles at once, so time it as a user calls it
            t0 = time.perf_counter()
            prep = jax.block_until_ready(prepare_system(system, **static))
            tc, tr = 0.0, time.perf_counter() - t0
            rec["setup_note"] = "not under an outer jit: compile included in the set-up time"
        else:
            prep, tc, tr = timed(jit_prepare, (system,), static)
        rec.update(setup_compile=tc, setup=tr)
        rec["ok"] = bool(np.all(np.asarray(prep.wiener.converged)))
        if prep.method == "cg":
            rec.update(it_wiener=float(np.mean(np.asarray(prep.wiener.iterations))), tol=static["options"].tol,
                       wiener_err_sigma=float(np.max(np.asarray(prep.wiener.err_sigma))))
        elif prep.method == "cholesky":
            rec["wiener_err_sigma"] = float(np.max(np.asarray(prep.wiener.err_sigma)))
        out["paths"][pname] = rec
        partial(out)
        if nd_p > 0:
            (dr, info), tc2, tr2 = timed(jit_draw, (key, prep), dict(ndraws=nd_p))
            rec.update(draw_compile=tc2, draw_total=tr2, per_draw=tr2 / nd_p)
            rec["ok"] = rec["ok"] and bool(np.all(np.asarray(info.draws.converged)))
            if prep.method == "cg":
                rec["it_draw"] = float(np.mean(np.asarray(info.draws.iterations)))
            del dr, info
        if prep.method == "cg":
            rec["it_wiener"] = float(np.mean(np.asarray(prep.wiener.iterations)))
            rec["wiener_err_sigma"] = float(np.max(np.asarray(prep.wiener.err_sigma)))
            rec["tol"] = static["options"].tol
            if pname == "cgD-mb":
                rel_mb = float(np.asarray(prep.wiener.rel_residual)[0])
                P0 = prep.precision[0]
                b0 = gcrsky.model.system.wiener_rhs(system)[0]
                tol = rel_mb * float(jnp.linalg.norm(b0))
                f = jax.jit(lambda P, b, tol: pcg(lambda x: P @ x, lambda r: r, b, jnp.zeros_like(b), tol=tol,
                                                  maxiter=NOPC_CAP)[1])
                t0 = time.perf_counter()
                inf0 = jax.block_until_ready(f(P0, b0, tol))
                k = int(inf0.iterations)
                conv = bool(inf0.converged)
                out["it_noPC"] = "capped" if (k >= NOPC_CAP and not conv) else (k if conv else f"{k}(nc)")
                out["it_noPC_s"] = time.perf_counter() - t0
                out["rel_target"] = rel_mb
        out["paths"][pname] = rec
        del prep
        partial(out)
    if "it_noPC" not in out:
        out["it_noPC"] = "n/a (no dense P)"

    if "mmode" in wanted:
        chk = mmode_check(system)
        if not chk.ok:
            out["paths"]["mmode"] = {"skip": "n/a: " + chk.reason}
        else:
            nd_p = int(ndr.get("mmode", ndraws))
            rec = {"load": load_now(), "ndraws": nd_p}
            t0 = time.perf_counter()  # bucket by bucket on the host (not one jit): compile included
            prep = jax.block_until_ready(prepare_mmode(system))
            tc, tr = 0.0, time.perf_counter() - t0
            rec.update(setup_compile=tc, setup=tr, setup_note="compile included (bucketed set-up)",
                       peak_MB_setup=peak_mb())
            (dr, info), tc2, tr2 = timed(draw_mmode, (key, prep), dict(ndraws=nd_p))
            rec.update(draw_compile=tc2, draw_total=tr2, per_draw=tr2 / nd_p)
            rec["ok"] = bool(np.all(np.asarray(info.draws.converged)))
            rec["wiener_rel_resid"] = float(np.max(np.asarray(prep.wiener.rel_residual)))
            rec["wiener_err_sigma"] = float(np.max(np.asarray(prep.wiener.err_sigma)))
            out["paths"]["mmode"] = rec
            del prep, dr, info
            partial(out)

    out["peak_MB"] = peak_mb()
    out["load_end"] = load_now()
    return out


# ---------------------------------------------------------------- driver and table


def fmt_path(r) -> str:
    if r is None:
        return "-"
    if "skip" in r:
        return "skip"
    s = f"{r['setup_compile']:.1f}+{r['setup']:.1f}"
    if "per_draw" in r:
        s += f"/{r['per_draw'] * 1e3:.3g}ms"
    elif r.get("ndraws", 0) > 0:
        s += "/(timeout)"
    if "it_wiener" in r:
        s += f" [{r['it_wiener']:.0f}" + (f",{r['it_draw']:.0f}]" if "it_draw" in r else "]")
    if not r.get("ok", True):
        s += "!"
    return s


PATHS = ["chol", "cgD-ny", "cgD-mb", "cgMF-ny", "mmode", "ds"]
HERA_PATHS = ["ds", "chol", "cgD-mb", "cgD-ny", "cgMF-ny", "cgMF-mb", "mmode"]


def _notes(results) -> list:
    notes = []
    for r in results:
        for p, v in r.get("paths", {}).items():
            if v and "skip" in v:
                notes.append(f"  {r['name']} {p}: skipped ({v['skip']})")
        if "rel_target" in r:
            notes.append(f"  {r['name']}: no-PC CG target rel. residual {r['rel_target']:.2e} "
                         f"(m-block Wiener solve), {r['it_noPC_s']:.1f} s")
        for p in ("mmode", "ds"):
            m = r.get("paths", {}).get(p)
            if m and "skip" not in m and "draw_total" in m:
                notes.append(f"  {r['name']} {p}: {m['ndraws']} draws in {m['draw_total']:.2f} s "
                             f"(+{m['draw_compile']:.1f} s compile), Wiener err {m.get('wiener_err_sigma', 0):.1e} sigma")
    return notes


def print_table(results) -> None:
    plain = [r for r in results if not r.get("red")]
    hera = [r for r in results if r.get("red")]
    if plain:
        print()
        print("config               n      Nbl  resp_s  prob_s  P_MB    peak_MB  auto     it_noPC   "
              + "  ".join(f"{p:<28}" for p in PATHS))
        for r in plain:
            if "error" in r:
                print(f"{r['name']:<20} FAILED: {r['error']}")
                continue
            cols = "  ".join(f"{fmt_path(r['paths'].get(p)):<28}" for p in PATHS)
            print(f"{r['name']:<20} {r['n']:<6} {r['nbl']:<4} {r['t_response']:>6.1f}  {r['t_problem']:>6.1f}  "
                  f"{r['P_MB']:<7.1f} {r['peak_MB']:<8.0f} {r.get('auto', '?'):<8} {r['it_noPC']!s:<9} {cols}")
        print("\npath cell: setup compile s + setup run s / time per draw (ms) [CG iters: Wiener, per draw]; "
              "'!' = a solve did not converge; ds only where N_d = 2 Nt Nbl < n")
        print("\n".join(_notes(plain)))
    if hera:
        print()
        print("config                      n      Nbl/all      N_d     resp_s  prob_s  peak_MB  load(1/5/15) auto      "
              + "  ".join(f"{p:<24}" for p in HERA_PATHS))
        for r in hera:
            if "error" in r and "N_d" not in r:
                print(f"{r['name']:<27} FAILED: {r['error']}")
                continue
            cols = "  ".join(f"{fmt_path(r['paths'].get(p)):<24}" for p in HERA_PATHS)
            nb = f"{r['nbl']}/{r['nbl_all']}"
            print(f"{r['name']:<27} {r['n']:<6} {nb:<12} {r['N_d']:<7} {r['t_response']:>6.1f}  "
                  f"{r['t_problem']:>6.1f}  {r['peak_MB']:<8.0f} {r['load_start']:<12} {r.get('auto', '?'):<9} {cols}")
        print("\npath cell: setup compile s + setup run s / time per draw (ms) [CG iters: Wiener, per draw]; "
              "Nbl = redundant groups (all baselines); resp_s = unique rows only (ring quadrature)")
        notes = _notes(hera)
        for r in hera:
            if "error" in r:
                notes.append(f"  {r['name']}: {r['error']}")
            if "N_d" not in r:
                continue
            nm = r["name"]
            for p in ("ds", "mmode"):
                m = r["paths"].get(p)
                if m and "skip" not in m and m.get("ndraws") == 200:
                    tot = m["setup_compile"] + m["setup"] + m["draw_compile"] + m["draw_total"]
                    notes.append(f"  {nm} {p}: set-up + 200 draws = {tot:.1f} s incl. compile "
                                 f"({m['setup'] + m['draw_total']:.1f} s run only); response {r['t_response']:.1f} s")
            ds, cg = r["paths"].get("ds"), r["paths"].get("cgMF-ny")
            for ch, (tc, tr, ld) in ((ds or {}).get("setup_by_chunk") or {}).items():
                notes.append(f"  {nm} ds set-up with DataSpaceOptions(time_chunk={ch}): {tc:.1f}+{tr:.1f} s (load {ld}); "
                             f"table cell: time_chunk={ds.get('time_chunk')}")
            if ds and cg and "per_draw" in ds and "per_draw" in cg:
                notes.append(f"  {nm}: per draw cgMF-ny / ds = {cg['per_draw'] / ds['per_draw']:.0f}x; "
                             f"set-up cgMF-ny / ds = {(cg['setup'] + cg['setup_compile']) / (ds['setup'] + ds['setup_compile']):.1f}x "
                             f"(CG Wiener {cg['it_wiener']:.0f} its, per draw {cg['it_draw']:.0f} its, tol {cg['tol']:g})")
            for p in ("cgMF-ny", "cgMF-mb"):
                m = r["paths"].get(p)
                if m and "it_wiener" in m and "per_draw" not in m:
                    notes.append(f"  {nm} {p}: Wiener solve to tol {m['tol']:g} sigma: {m['it_wiener']:.0f} iterations, "
                                 f"{m['setup']:.1f} s (+{m['setup_compile']:.1f} s compile), err {m['wiener_err_sigma']:.1e}, load {m['load']}")
            e = r.get("ds_estimate")
            if e and r["paths"].get("ds", {}).get("skip"):
                notes.append(f"  {nm} ds: N_d = {e['N_d']}, D = {e['D_GB']:.1f} GB (x4 peak ~{e['mem_GB']:.0f} GB), "
                             f"D build ~{e['flop_D']:.1e} flop, Cholesky ~{e['flop_chol']:.1e} flop")
            rc = r.get("resp_compare")
            if rc:
                k = r["nbl"] / rc["nbl"]
                notes.append(f"  {nm} response on {rc['nbl']} unique rows: rings {rc['t_rings']:.1f} s, healpy SHT "
                             f"{rc['t_sht']:.1f} s (load {rc['load']}); max |R_rings - R_sht| / max |R| = {rc['rel_max']:.1e}, "
                             f"worst row {rc['rel_row']:.1e}; linear extrapolation to {r['nbl']} rows: rings "
                             f"~{rc['t_rings'] * k:.0f} s (measured {r['t_response']:.1f} s), SHT ~{rc['t_sht'] * k:.0f} s")
        print("\n".join(notes))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny grid (< 2 min)")
    ap.add_argument("--hera", action="store_true", help="the issue rows (HERA_GRID, redundancy-compressed; ~1 h on a loaded 2-core box)")
    ap.add_argument("--only", nargs="+", help="configuration names (see --list)")
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--one", help="run one configuration in this process")
    ap.add_argument("--json", action="store_true", help="with --one: print the result as JSON")
    ap.add_argument("--timeout", type=float, default=None,
                    help="seconds per configuration (default 300, or the row's own in HERA_SPEC)")
    a = ap.parse_args(argv)
    grid = _red(HERA_GRID) if a.hera else (QUICK_GRID if a.quick else DEFAULT_GRID)
    if a.list:
        print("\n".join(name_of(c) for c in grid))
        return 0
    if a.one:
        res = run_one(parse_name(a.one, grid))
        print("JSON:" + json.dumps(res) if a.json else res)
        return 0
    if a.only:
        grid = [parse_name(s, grid) for s in a.only]
    results = []
    t_all = time.perf_counter()
    for c in grid:
        nm = name_of(c)
        timeout = a.timeout if a.timeout is not None else spec_of(c).get("timeout", 300.0)
        t0 = time.perf_counter()
        try:
            p = subprocess.run([sys.executable, os.path.abspath(__file__), "--one", nm, "--json"],
                               capture_output=True, text=True, timeout=timeout)
            line = [s for s in p.stdout.splitlines() if s.startswith("JSON:")]
            if p.returncode != 0 or not line:
                res = {"name": nm, "error": (p.stderr.strip().splitlines() or ["?"])[-1]}
            else:
                res = json.loads(line[-1][5:])
        except subprocess.TimeoutExpired as e:
            so = e.stdout.decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
            part = [s for s in so.splitlines() if s.startswith("PARTIAL:")]
            res = json.loads(part[-1][8:]) if part else {"name": nm}
            res["error"] = f"timed out after {timeout:.0f} s" + (" (partial results kept)" if part else "")
        res["wall"] = time.perf_counter() - t0
        res.setdefault("red", len(c) > 6 and bool(c[6]))
        print(f"{nm}: {res['wall']:.1f} s wall, load {load_now()}"
              + (f"  ({res['error']})" if "error" in res else ""), flush=True)
        print("RESULT:" + json.dumps(res), flush=True)  # every field, for the record
        results.append(res)
    print_table(results)
    print(f"\ntotal {time.perf_counter() - t_all:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
