#!/usr/bin/env bash
# Waits for a Kubernetes Job to end: exit 0 when it completes, exit 1 as
# soon as it fails (or at the timeout). `kubectl wait
# --for=condition=complete` alone waits out its whole timeout when the Job
# fails, since the Complete condition then never comes; so this waits for
# Complete and for Failed at once and stops at the first.
#
#   deploy/k8s/wait-job.sh JOB [TIMEOUT]        (TIMEOUT: default 24h)
#
# The distributed bake:
#   kubectl apply -f deploy/k8s/pvc.yaml -f deploy/k8s/shard-job.yaml
#   deploy/k8s/wait-job.sh shadowcull-shards 24h &&
#     kubectl apply -f deploy/k8s/merge-job.yaml &&
#     deploy/k8s/wait-job.sh shadowcull-merge 6h
set -u
job=${1:?usage: wait-job.sh JOB [TIMEOUT]}
timeout=${2:-24h}

kubectl wait --for=condition=complete --timeout="$timeout" "job/$job" >/dev/null &
complete=$!
kubectl wait --for=condition=failed --timeout="$timeout" "job/$job" >/dev/null &
failed=$!
# The first wait to return (a condition met, the timeout, or an error)
# ends both; the Job's conditions then say which.
wait -n
kill "$complete" "$failed" 2>/dev/null
wait 2>/dev/null

state=$(kubectl get "job/$job" -o jsonpath='{.status.conditions[?(@.type=="Complete")].status}')
if [ "$state" = True ]; then
  echo "job/$job completed"
  exit 0
fi
echo "job/$job did not complete (failed, or still running at the ${timeout} timeout):" >&2
kubectl get "job/$job" \
  -o jsonpath='{range .status.conditions[*]}  {.type}={.status}: {.reason} {.message}{"\n"}{end}' >&2
echo "  failed pods: kubectl logs -l job-name=$job --prefix" >&2
exit 1
