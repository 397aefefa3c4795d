//! The sequences whose background a worker of this process computes now
//! (module `preprocessing`), so that two workers of one process do not
//! compute one twice.

use crate::service::store::SequenceId;

/// The sequences whose background a worker of this process computes now.
#[derive(Debug, Default)]
pub struct Computing(std::sync::Mutex<std::collections::HashSet<SequenceId>>);

/// A sequence's background being computed, until dropped.
pub struct ComputingGuard<'a>(&'a Computing, SequenceId);

impl Computing {
    /// Marks the sequence's background as being computed, unless it is.
    pub fn start(&self, sequence_id: SequenceId) -> Option<ComputingGuard<'_>> {
        let mut set = self.0.lock().unwrap_or_else(|e| e.into_inner());
        set.insert(sequence_id)
            .then(|| ComputingGuard(self, sequence_id))
    }
}

impl Drop for ComputingGuard<'_> {
    fn drop(&mut self) {
        let mut set = self.0 .0.lock().unwrap_or_else(|e| e.into_inner());
        set.remove(&self.1);
    }
}
