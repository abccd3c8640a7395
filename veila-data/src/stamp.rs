//! Time stamps for written reports: UTC calendar dates without a date-time dependency, and a "now"
//! that honours `SOURCE_DATE_EPOCH` so reports can be made reproducible.

/// UTC date and time of a Unix timestamp, `YYYY-MM-DD HH:MM:SS UTC` (proleptic Gregorian calendar).
pub fn utc_string(unix_s: i64) -> String {
    let days = unix_s.div_euclid(86_400);
    let secs = unix_s.rem_euclid(86_400);
    // civil date from days since 1970-01-01 (400-year eras)
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02} {:02}:{:02}:{:02} UTC",
        secs / 3600,
        secs / 60 % 60,
        secs % 60
    )
}

/// The time a report is stamped with, as [`utc_string`]: `SOURCE_DATE_EPOCH` when set (reproducible
/// reports), else now.
pub fn report_time() -> String {
    let from_env = std::env::var("SOURCE_DATE_EPOCH")
        .ok()
        .and_then(|s| s.trim().parse::<i64>().ok());
    let t = from_env.unwrap_or_else(|| {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs() as i64)
            .unwrap_or(0)
    });
    utc_string(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utc_dates_hand_checked() {
        assert_eq!(utc_string(0), "1970-01-01 00:00:00 UTC");
        assert_eq!(utc_string(951_782_400), "2000-02-29 00:00:00 UTC");
        assert_eq!(utc_string(1_795_153_261), "2026-11-20 05:41:01 UTC"); // python datetime
        assert_eq!(utc_string(-1), "1969-12-31 23:59:59 UTC");
        assert_eq!(utc_string(4_107_542_400), "2100-03-01 00:00:00 UTC");
    }
}
