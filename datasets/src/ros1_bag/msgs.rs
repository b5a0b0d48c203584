//! ROS 1 messages as the bag stores them (the ROS 1 serialisation: little-endian, no
//! alignment, `u32` length before strings and variable arrays): parsers of the few
//! `sensor_msgs` types shoal reads. A message too short or with a bad length is an error,
//! never a panic.

/// A ROS 1 time: seconds and nanoseconds since the epoch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Time {
    /// Seconds.
    pub sec: u32,
    /// Nanoseconds.
    pub nsec: u32,
}

impl Time {
    /// The time in ns; `None` when `nsec` is not below 1e9.
    pub fn to_ns(self) -> Option<i64> {
        (self.nsec < 1_000_000_000)
            .then(|| i64::from(self.sec) * 1_000_000_000 + i64::from(self.nsec))
    }
}

/// A reader over a message's bytes.
struct Rd<'a> {
    b: &'a [u8],
    p: usize,
}

impl<'a> Rd<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self.p.checked_add(n).filter(|e| *e <= self.b.len());
        let Some(end) = end else {
            return Err(format!(
                "message of {} bytes ends before byte {} (a field of {n} bytes at {})",
                self.b.len(),
                self.p.saturating_add(n),
                self.p
            ));
        };
        let s = &self.b[self.p..end];
        self.p = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8, String> {
        Ok(self.take(1)?[0])
    }
    fn u32(&mut self) -> Result<u32, String> {
        let s = self.take(4)?;
        Ok(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
    }
    fn f64(&mut self) -> Result<f64, String> {
        let s = self.take(8)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(s);
        Ok(f64::from_le_bytes(a))
    }
    fn f64s<const N: usize>(&mut self) -> Result<[f64; N], String> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64()?;
        }
        Ok(out)
    }
    fn bytes(&mut self) -> Result<&'a [u8], String> {
        let n = self.u32()? as usize;
        self.take(n)
    }
    fn string(&mut self) -> Result<&'a str, String> {
        std::str::from_utf8(self.bytes()?).map_err(|e| format!("a string is not UTF-8: {e}"))
    }
    /// `std_msgs/Header`: its stamp (the sequence number and frame are skipped).
    fn header(&mut self) -> Result<Time, String> {
        self.u32()?;
        let t = Time {
            sec: self.u32()?,
            nsec: self.u32()?,
        };
        self.string()?;
        Ok(t)
    }
}

/// `sensor_msgs/Image`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Image<'a> {
    /// Header stamp.
    pub stamp: Time,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding.
    pub encoding: &'a str,
    /// 1 for big-endian multi-byte pixels.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// Pixels.
    pub data: &'a [u8],
}

/// Parses a `sensor_msgs/Image`.
pub fn image(b: &[u8]) -> Result<Image<'_>, String> {
    let mut r = Rd { b, p: 0 };
    Ok(Image {
        stamp: r.header()?,
        height: r.u32()?,
        width: r.u32()?,
        encoding: r.string()?,
        is_bigendian: r.u8()?,
        step: r.u32()?,
        data: r.bytes()?,
    })
}

/// `sensor_msgs/CompressedImage`: stamp, format, data.
pub fn compressed_image(b: &[u8]) -> Result<(Time, &str, &[u8]), String> {
    let mut r = Rd { b, p: 0 };
    Ok((r.header()?, r.string()?, r.bytes()?))
}

/// `sensor_msgs/Imu`: stamp, angular velocity, linear acceleration.
pub fn imu(b: &[u8]) -> Result<(Time, [f64; 3], [f64; 3]), String> {
    let mut r = Rd { b, p: 0 };
    let stamp = r.header()?;
    r.f64s::<4>()?;
    r.f64s::<9>()?;
    let gyro = r.f64s::<3>()?;
    r.f64s::<9>()?;
    let accel = r.f64s::<3>()?;
    Ok((stamp, gyro, accel))
}

/// `sensor_msgs/CameraInfo`: what the camera model needs.
pub fn camera_info(b: &[u8]) -> Result<crate::mcap_bag::CameraInfoValues, String> {
    let mut r = Rd { b, p: 0 };
    r.header()?;
    let height = r.u32()?;
    let width = r.u32()?;
    let distortion_model = r.string()?.to_string();
    let n = r.u32()? as usize;
    if n > 16 {
        return Err(format!("CameraInfo with {n} distortion coefficients"));
    }
    let d = (0..n)
        .map(|_| r.f64())
        .collect::<Result<Vec<f64>, String>>()?;
    let k = r.f64s::<9>()?;
    Ok(crate::mcap_bag::CameraInfoValues {
        width,
        height,
        distortion_model,
        d,
        k,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An Image laid out by hand: seq, stamp, frame "c", 1x2 mono8, step 2, two pixels;
    /// every cut of it is an error.
    #[test]
    fn image_layout_and_cuts() {
        let mut b = vec![9, 0, 0, 0, 7, 0, 0, 0, 5, 0, 0, 0, 1, 0, 0, 0, b'c'];
        b.extend_from_slice(&[1, 0, 0, 0, 2, 0, 0, 0, 5, 0, 0, 0]);
        b.extend_from_slice(b"mono8");
        b.extend_from_slice(&[0, 2, 0, 0, 0, 2, 0, 0, 0, 10, 20]);
        let m = image(&b).unwrap();
        assert_eq!(m.stamp.to_ns(), Some(7_000_000_005));
        assert_eq!((m.width, m.height, m.encoding, m.step), (2, 1, "mono8", 2));
        assert_eq!(m.data, &[10, 20]);
        for cut in 0..b.len() {
            assert!(image(&b[..cut]).is_err(), "cut at {cut}");
        }
    }
}
