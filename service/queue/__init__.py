"""The durable job queue: jobs live in the database; workers claim them atomically, hold a lease renewed by
heartbeats, and a reaper re-queues jobs whose worker died. See store.py (claim/lease/heartbeat/reaper),
runner.py (the CPU work in a pool process) and worker.py (the loop; also the dispatcher `calib serve` embeds)."""
