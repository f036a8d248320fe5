//! The time age retention counts from: the wall clock, as far as the monotonic clock
//! confirms it. A shop-floor PC's clock is set by hand, by a time server that may be
//! wrong, or from a dead RTC; a forward step by more than `retention_days` would
//! otherwise delete the whole recorded history at the next retention pass.

use std::time::Instant;

/// A step of the wall clock against the monotonic one smaller than this is an
/// ordinary correction (NTP, a hand-set second); larger ones are logged.
pub const STEP_MS: i64 = 60_000;

/// What changed at a reading of [`RetentionClock::now_ms`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ClockEvent {
    /// The wall clock stepped ahead by this many ms: retention does not follow it.
    StepAhead(i64),
    /// The wall clock stepped back by this many ms: retention follows it (it deletes
    /// later, never earlier).
    StepBack(i64),
    /// The wall clock is in line with the monotonic clock again after a step ahead.
    BackInLine,
    /// At start, the wall clock is this many ms past the newest record, more than
    /// the retention: age retention would delete every record, so it waits.
    StartAhead(i64),
    /// At start, the wall clock is this many ms before the newest record.
    StartBehind(i64),
}

/// The wall clock trusted for deleting: a step back is taken at once (it only
/// delays deletion); a step ahead is not, and retention counts on from the time
/// before it by the monotonic clock until the wall clock comes back in line or
/// the gateway restarts.
#[derive(Debug, Default)]
pub struct RetentionClock {
    /// The monotonic and the trusted wall time (ms) read together last.
    anchor: Option<(Instant, i64)>,
    /// How far the wall clock is ahead of the trusted time now (0: in line).
    ahead_ms: i64,
}

impl RetentionClock {
    /// How far the wall clock is ahead of the time retention counts from (0: in line).
    pub fn ahead_ms(&self) -> i64 {
        self.ahead_ms
    }

    /// Whether [`Self::start`] was called.
    pub fn started(&self) -> bool {
        self.anchor.is_some()
    }

    /// Anchors the clock at start, given the newest record's time: a wall clock past
    /// it by more than `retention_ms` (a clock set wrong while the gateway was
    /// stopped, or a PC off that long) is not trusted, and retention counts from the
    /// newest record until the next start. Nothing is lost by waiting if the PC was
    /// off; the whole recording would be if the clock is wrong. Returns what
    /// [`Self::now_ms`] does.
    pub fn start(
        &mut self,
        mono: Instant,
        wall_ms: i64,
        newest_ms: Option<i64>,
        retention_ms: i64,
    ) -> (i64, Option<ClockEvent>) {
        let (trusted_ms, event) = match newest_ms {
            Some(n) if wall_ms.saturating_sub(n) > retention_ms => {
                (n, Some(ClockEvent::StartAhead(wall_ms - n)))
            }
            Some(n) if n.saturating_sub(wall_ms) > STEP_MS => {
                (wall_ms, Some(ClockEvent::StartBehind(n - wall_ms)))
            }
            _ => (wall_ms, None),
        };
        self.anchor = Some((mono, trusted_ms));
        self.ahead_ms = wall_ms - trusted_ms;
        (trusted_ms, event)
    }

    /// The time (Unix ms) retention may count from, given the monotonic clock `mono`
    /// and the wall clock `wall_ms` read at the same instant, and what changed.
    pub fn now_ms(&mut self, mono: Instant, wall_ms: i64) -> (i64, Option<ClockEvent>) {
        let Some((mono0, trusted0_ms)) = self.anchor else {
            return self.start(mono, wall_ms, None, 0);
        };
        let elapsed_ms =
            i64::try_from(mono.saturating_duration_since(mono0).as_millis()).unwrap_or(i64::MAX);
        let trusted_ms = trusted0_ms.saturating_add(elapsed_ms);
        let ahead_ms = wall_ms.saturating_sub(trusted_ms);
        if ahead_ms > STEP_MS {
            // Stay on the old anchor: the trusted time runs on by the monotonic clock.
            let event = ((ahead_ms - self.ahead_ms).abs() > STEP_MS)
                .then_some(ClockEvent::StepAhead(ahead_ms - self.ahead_ms));
            if event.is_some() {
                self.ahead_ms = ahead_ms;
            }
            return (trusted_ms, event);
        }
        let event = if self.ahead_ms != 0 {
            Some(ClockEvent::BackInLine)
        } else if ahead_ms < -STEP_MS {
            Some(ClockEvent::StepBack(-ahead_ms))
        } else {
            None
        };
        self.ahead_ms = 0;
        self.anchor = Some((mono, wall_ms));
        (wall_ms, event)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    const DAY_MS: i64 = 86_400_000;
    const T0_MS: i64 = 1_790_000_000_000;

    /// Readings of the clock `mono_s` seconds after `start` with the wall clock at
    /// `wall_ms`.
    fn at(
        c: &mut RetentionClock,
        start: Instant,
        mono_s: u64,
        wall_ms: i64,
    ) -> (i64, Option<ClockEvent>) {
        c.now_ms(start + Duration::from_secs(mono_s), wall_ms)
    }

    #[test]
    fn follows_a_wall_clock_in_line_and_small_corrections() {
        let mut c = RetentionClock::default();
        let s = Instant::now();
        assert_eq!(at(&mut c, s, 0, T0_MS), (T0_MS, None));
        assert_eq!(at(&mut c, s, 60, T0_MS + 60_000), (T0_MS + 60_000, None));
        // An NTP step of 30 s either way is taken as it is.
        assert_eq!(at(&mut c, s, 120, T0_MS + 150_000), (T0_MS + 150_000, None));
        assert_eq!(at(&mut c, s, 180, T0_MS + 150_000), (T0_MS + 150_000, None));
    }

    #[test]
    fn a_step_ahead_is_not_followed_until_it_is_set_back() {
        let mut c = RetentionClock::default();
        let s = Instant::now();
        at(&mut c, s, 0, T0_MS);
        // Set a year ahead by a typo: retention counts on from the time before.
        let wall = T0_MS + 60_000 + 365 * DAY_MS;
        assert_eq!(
            at(&mut c, s, 60, wall),
            (T0_MS + 60_000, Some(ClockEvent::StepAhead(365 * DAY_MS)))
        );
        // Told once, and the trusted time runs on by the monotonic clock.
        assert_eq!(at(&mut c, s, 120, wall + 60_000), (T0_MS + 120_000, None));
        // A second step ahead is told again.
        assert_eq!(
            at(&mut c, s, 180, wall + 120_000 + DAY_MS),
            (T0_MS + 180_000, Some(ClockEvent::StepAhead(DAY_MS)))
        );
        // Set right again.
        assert_eq!(
            at(&mut c, s, 240, T0_MS + 240_000),
            (T0_MS + 240_000, Some(ClockEvent::BackInLine))
        );
        assert_eq!(at(&mut c, s, 300, T0_MS + 300_000), (T0_MS + 300_000, None));
    }

    #[test]
    fn a_start_far_past_the_newest_record_waits_and_one_before_it_is_told() {
        let s = Instant::now();
        let newest = Some(T0_MS);
        // Started a year on: retention of 90 days would delete everything.
        let mut c = RetentionClock::default();
        let wall = T0_MS + 365 * DAY_MS;
        assert_eq!(
            c.start(s, wall, newest, 90 * DAY_MS).1,
            Some(ClockEvent::StartAhead(365 * DAY_MS))
        );
        assert_eq!(
            at(&mut c, s, 60, wall + 60_000),
            (T0_MS + 60_000, None),
            "counts on from the newest record"
        );
        // Set right while running: in line again.
        assert_eq!(
            at(&mut c, s, 120, T0_MS + 120_000),
            (T0_MS + 120_000, Some(ClockEvent::BackInLine))
        );
        // Started a day on: followed.
        let mut c = RetentionClock::default();
        assert_eq!(c.start(s, T0_MS + DAY_MS, newest, 90 * DAY_MS).1, None);
        assert_eq!(
            at(&mut c, s, 60, T0_MS + DAY_MS + 60_000).0,
            T0_MS + DAY_MS + 60_000
        );
        // Started before the newest record (a dead RTC): followed, and told.
        let mut c = RetentionClock::default();
        let y2000_ms = 946_684_800_000;
        assert_eq!(
            c.start(s, y2000_ms, newest, 90 * DAY_MS).1,
            Some(ClockEvent::StartBehind(T0_MS - y2000_ms))
        );
        // An empty database: followed.
        let mut c = RetentionClock::default();
        assert_eq!(c.start(s, wall, None, 90 * DAY_MS).1, None);
    }

    #[test]
    fn a_step_back_is_followed_and_told() {
        let mut c = RetentionClock::default();
        let s = Instant::now();
        at(&mut c, s, 0, T0_MS);
        let back = T0_MS + 60_000 - DAY_MS;
        assert_eq!(
            at(&mut c, s, 60, back),
            (back, Some(ClockEvent::StepBack(DAY_MS)))
        );
        // Then it is in line from there.
        assert_eq!(at(&mut c, s, 120, back + 60_000), (back + 60_000, None));
    }

    #[test]
    fn a_dead_rtc_set_right_while_running_deletes_nothing_until_a_restart() {
        // Started at 2000-01-01, then a time server sets the clock to now.
        let mut c = RetentionClock::default();
        let s = Instant::now();
        let y2000_ms = 946_684_800_000;
        at(&mut c, s, 0, y2000_ms);
        let (trusted, event) = at(&mut c, s, 60, T0_MS);
        assert_eq!(trusted, y2000_ms + 60_000);
        assert!(matches!(event, Some(ClockEvent::StepAhead(_))));
        // A restart trusts the wall clock again.
        let mut c = RetentionClock::default();
        assert_eq!(at(&mut c, s, 120, T0_MS + 60_000), (T0_MS + 60_000, None));
    }
}
