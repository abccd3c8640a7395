//! How a long run of the application (a training recipe, a benchmark) shows itself to the binary
//! that drives it: its story as lines ([`Progress::line`]) and each long step as a bar
//! ([`Progress::bar`]). The library decides what happens and says so; the driver decides how it is
//! drawn (`cargo xtask` draws terminal bars; `()` shows nothing).

/// The driver's side of a long run. Called from the run's threads, hence `Sync`.
pub trait Progress: Sync {
    /// A line of the run's story (a stage done, a file written, a row's time).
    fn line(&self, text: &str);

    /// A long step of `total` units (frames, scans, updates) named `label` begins; it ends when
    /// the returned bar is dropped.
    fn bar(&self, label: &str, total: u64) -> Box<dyn Bar + '_>;
}

/// One long step's progress (from any thread).
pub trait Bar: Sync {
    /// One more unit is done.
    fn inc(&self);

    /// `done` units are done; `status` is a short word on how it goes (a training loss).
    fn set(&self, done: u64, status: &str);
}

/// Shows nothing.
impl Progress for () {
    fn line(&self, _text: &str) {}

    fn bar(&self, _label: &str, _total: u64) -> Box<dyn Bar + '_> {
        Box::new(())
    }
}

/// Shows nothing.
impl Bar for () {
    fn inc(&self) {}

    fn set(&self, _done: u64, _status: &str) {}
}

/// The lines a run tells, kept for a test to read (bars show nothing).
#[cfg(all(test, feature = "sim"))]
#[derive(Default)]
pub(crate) struct Lines(pub(crate) std::sync::Mutex<Vec<String>>);

#[cfg(all(test, feature = "sim"))]
impl Progress for Lines {
    fn line(&self, text: &str) {
        self.0.lock().unwrap().push(text.to_string());
    }

    fn bar(&self, _label: &str, _total: u64) -> Box<dyn Bar + '_> {
        Box::new(())
    }
}
