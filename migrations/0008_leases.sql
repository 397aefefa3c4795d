-- Leases (issue 17): a claimed job is held for a time, renewed by its
-- worker's heartbeat; a job whose lease has run out (its worker died,
-- hung or lost the database) is claimable again at once by any worker
-- process. Times are UTC RFC 3339 text from the database's clock, as
-- elsewhere; only the database's clock is ever compared with them.
--
-- lease_token is the fencing token: incremented at every claim, and every
-- completion, failure or hand-back of an attempt is an UPDATE ... WHERE
-- id = ? AND lease_token = ? that checks the rows it changed, in the same
-- transaction as the attempt's results, so a worker that lost its lease
-- writes nothing. locked_by (migration 1) names the lease's owner: host,
-- process id and a random part, then the worker's index in its process.
ALTER TABLE jobs ADD COLUMN lease_until TEXT;
ALTER TABLE jobs ADD COLUMN lease_token INTEGER NOT NULL DEFAULT 0;
-- Jobs a stopped process left running have no lease (NULL): their lease
-- has run out, and the next claim queues them again.

-- Every claim of a job, in order: its token, who claimed it and when, and
-- how the attempt ended (NULL while it runs): succeeded, failed,
-- released (queued again after a passing failure or at a shutdown),
-- given_back (not counted: a full disk, or deferred), or expired (its
-- lease ran out and the job was queued again for another worker). The
-- history of takeovers that the API shows.
CREATE TABLE job_claims (
    job_id      INTEGER NOT NULL REFERENCES jobs (id),
    token       INTEGER NOT NULL,
    worker      TEXT    NOT NULL,
    claimed_at  TEXT    NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    outcome     TEXT    CHECK (outcome IN ('succeeded', 'failed', 'released', 'given_back', 'expired')),
    ended_at    TEXT,
    PRIMARY KEY (job_id, token)
);

-- The claim finds the running jobs whose lease has run out.
CREATE INDEX jobs_running_lease ON jobs (lease_until) WHERE state = 'running';

-- One tracker per tracking run at a time, across processes: the run's
-- lease, taken by the process that advances it, renewed by heartbeat
-- while it holds the run's tracker in memory, taken over (the tracker
-- rebuilt by replay) once it has run out. lease_token is incremented at
-- every change of owner and fences the frames the holder stores.
ALTER TABLE tracking_runs ADD COLUMN lease_owner TEXT;
ALTER TABLE tracking_runs ADD COLUMN lease_until TEXT;
ALTER TABLE tracking_runs ADD COLUMN lease_token INTEGER NOT NULL DEFAULT 0;
