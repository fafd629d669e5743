#!/bin/sh
# One feasibility map (zhang2022 Fig. 1, the LESO over zeta1 x w1/|w0|) computed by two
# processes on this machine with jax.distributed: each process is one CPU device, every
# chunk of the sweep is split between them, and process 0 writes the outputs.
#
#   examples/distributed_feasibility.sh [OUT [PORT]] [-- more pmsmjax feasibility options]
#
# OUT: output folder (default results/distributed); PORT: a free TCP port for the
# coordinator (default 12355). On several hosts run the same command once on each host,
# with --coordinator HOST0:PORT (HOST0: the host of process 0), --num-processes P and
# --process-id 0..P-1, and an OUT on a file system that every host sees.
# PMSMJAX: how to start the command line (default: pmsmjax).
set -u
OUT=${1:-results/distributed}
PORT=${2:-12355}
[ $# -gt 0 ] && shift
[ $# -gt 0 ] && [ "$1" != "--" ] && shift
[ $# -gt 0 ] && [ "$1" = "--" ] && shift
PMSMJAX=${PMSMJAX:-pmsmjax}
export JAX_PLATFORMS=cpu  # one CPU device per process

pids=""
for ID in 0 1; do
    $PMSMJAX feasibility --observer leso --set L_d=1e-3 --set L_q=4.9e-3 --i-q 2 \
        --zeta1 0:5:51 --ratio 0:2:41 --speed 0.5 --chunk-size 512 --batch-size 64 \
        --coordinator "localhost:$PORT" --num-processes 2 --process-id "$ID" \
        --out "$OUT" "$@" &
    pids="$pids $!"
done
status=0
for pid in $pids; do
    wait "$pid" || status=1
done
exit $status
