//! The worker threads that split one kernel launch into chunks ([`super::CpuModule::run_parallel`]).
//!
//! A backward pass launches five short kernels per step (50–500 µs each at 10k tets), one after
//! the other. A pool whose threads sleep between launches (rayon's) pays a wake-up and a join
//! per launch, which on this project's 2-core VM cost more than the second core saved. Here a
//! worker spins for a while after each job ([`SPIN`]) before it sleeps, so a sequence of
//! launches finds it awake; a launch publishes its chunks, the calling thread claims chunks
//! too, and it returns when every chunk is done.
//!
//! Chunks are claimed one at a time under a mutex (a launch has a few chunks, so the lock is
//! cheap), which also keeps a late worker from touching a finished launch: it only ever runs a
//! chunk it claimed, and the launch waits for every claimed chunk. Which thread runs which
//! chunk changes nothing in the result: the chunks are fixed by the launch alone.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Condvar, Mutex, OnceLock};
use std::time::{Duration, Instant};

/// How long an idle worker keeps spinning before it sleeps.
const SPIN: Duration = Duration::from_micros(200);

/// A chunk runner: `(data, chunk index)`.
type ChunkFn = unsafe fn(*const (), usize);

#[derive(Clone, Copy)]
struct Job {
    run: ChunkFn,
    data: *const (),
    chunks: usize,
    next: usize,
}

// SAFETY: `data` is only dereferenced by `run` for a claimed chunk while the launching thread
// waits in `run_chunks` (see there), which keeps what it points to alive and shared-readable.
unsafe impl Send for Job {}

struct Pool {
    job: Mutex<Option<Job>>,
    /// Bumped at each published launch: what spinning workers watch.
    epoch: AtomicU64,
    /// Chunks of the current launch finished.
    done: AtomicUsize,
    sleepers: Mutex<usize>,
    wake: Condvar,
    workers: usize,
    /// Set by [`park`]: idle workers sleep at once instead of spinning.
    parked: AtomicBool,
}

static POOL: OnceLock<&'static Pool> = OnceLock::new();

fn pool() -> &'static Pool {
    POOL.get_or_init(|| {
        let workers = std::thread::available_parallelism().map_or(1, |n| n.get().min(64)) - 1;
        let p: &'static Pool = Box::leak(Box::new(Pool {
            job: Mutex::new(None),
            epoch: AtomicU64::new(0),
            done: AtomicUsize::new(0),
            sleepers: Mutex::new(0),
            wake: Condvar::new(),
            workers,
            parked: AtomicBool::new(false),
        }));
        for i in 0..workers {
            std::thread::Builder::new()
                .name(format!("softc-cpu-{i}"))
                .spawn(move || p.work())
                .expect("the CPU backend's worker threads start");
        }
        p
    })
}

impl Pool {
    /// Claim the next chunk of the current launch, if one is left.
    fn claim(&self) -> Option<(ChunkFn, *const (), usize)> {
        let mut job = self.job.lock().unwrap_or_else(|e| e.into_inner());
        let j = job.as_mut()?;
        if j.next >= j.chunks {
            return None;
        }
        j.next += 1;
        Some((j.run, j.data, j.next - 1))
    }

    /// Run claimed chunks until none is left.
    fn drain(&self) {
        while let Some((run, data, c)) = self.claim() {
            // SAFETY: the chunk was claimed from the current launch, whose caller waits in
            // `run_chunks` until this chunk is counted done.
            unsafe { run(data, c) };
            self.done.fetch_add(1, Ordering::Release);
        }
    }

    fn work(&self) {
        let mut seen = 0;
        loop {
            let start = Instant::now();
            let mut spins = 0u32;
            loop {
                let e = self.epoch.load(Ordering::Acquire);
                if e != seen {
                    seen = e;
                    break;
                }
                std::hint::spin_loop();
                spins += 1;
                if spins.is_multiple_of(256)
                    && (start.elapsed() > SPIN || self.parked.load(Ordering::Relaxed))
                {
                    // Sleep until the next launch (checked under the lock `run_chunks` notifies
                    // under, so a launch published now is not missed).
                    let mut sleepers = self.sleepers.lock().unwrap_or_else(|e| e.into_inner());
                    while self.epoch.load(Ordering::Acquire) == seen {
                        *sleepers += 1;
                        sleepers = self.wake.wait(sleepers).unwrap_or_else(|e| e.into_inner());
                        *sleepers -= 1;
                    }
                    drop(sleepers);
                    seen = self.epoch.load(Ordering::Acquire);
                    break;
                }
            }
            self.drain();
        }
    }
}

/// Run `chunks` chunks, `run(data, c)` for each `c`, on the calling thread and the pool's
/// workers; returns when all are done. Launches from several threads at once are serialized.
///
/// # Safety
/// `run(data, c)` must be safe to call for every `c < chunks`, concurrently for different
/// `c`, while this call lasts.
pub(super) unsafe fn run_chunks(run: ChunkFn, data: *const (), chunks: usize) {
    let p = pool();
    if p.workers == 0 || chunks <= 1 {
        for c in 0..chunks {
            // SAFETY: forwarded from the caller.
            unsafe { run(data, c) };
        }
        return;
    }
    p.parked.store(false, Ordering::Relaxed);
    static LAUNCH: Mutex<()> = Mutex::new(());
    let _one_at_a_time = LAUNCH.lock().unwrap_or_else(|e| e.into_inner());
    {
        let mut job = p.job.lock().unwrap_or_else(|e| e.into_inner());
        p.done.store(0, Ordering::Relaxed);
        *job = Some(Job {
            run,
            data,
            chunks,
            next: 0,
        });
    }
    p.epoch.fetch_add(1, Ordering::AcqRel);
    {
        let sleepers = p.sleepers.lock().unwrap_or_else(|e| e.into_inner());
        if *sleepers > 0 {
            p.wake.notify_all();
        }
    }
    p.drain();
    let mut spins = 0u32;
    while p.done.load(Ordering::Acquire) < chunks {
        // A worker runs its last chunk: wait for it, giving the core away now and then in
        // case that worker shares it.
        std::hint::spin_loop();
        spins += 1;
        if spins.is_multiple_of(4096) {
            std::thread::yield_now();
        }
    }
    // Every chunk ran: nothing refers to `data` any more.
    *p.job.lock().unwrap_or_else(|e| e.into_inner()) = None;
}

/// Send idle workers to sleep now rather than after their spin: for code about to run threads
/// of its own (the compiled time loop), which spinning workers would slow on a small machine.
pub(super) fn park() {
    if let Some(p) = POOL.get() {
        p.parked.store(true, Ordering::Relaxed);
    }
}
