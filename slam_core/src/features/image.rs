//! Plain 8-bit gray images: a borrowed view ([`GrayImage`]) and an owned buffer ([`GrayBuffer`]).

use crate::CoreError;

/// A borrowed 8-bit gray image: `height` rows of `width` pixels, rows `stride` bytes apart.
///
/// Pixel `(x, y)` is `data[y * stride + x]`. The view is checked once at construction, so the
/// algorithms can index it without further checks.
#[derive(Debug, Clone, Copy)]
pub struct GrayImage<'a> {
    data: &'a [u8],
    width: usize,
    height: usize,
    stride: usize,
}

impl<'a> GrayImage<'a> {
    /// Wraps `data` as a `width` x `height` image whose rows are `stride` bytes apart.
    ///
    /// Errors when a size is zero, `stride < width`, or `data` is shorter than
    /// `(height - 1) * stride + width`.
    pub fn new(
        data: &'a [u8],
        width: usize,
        height: usize,
        stride: usize,
    ) -> Result<Self, CoreError> {
        if width == 0 || height == 0 {
            return Err(CoreError::InvalidArgument(format!(
                "image size {width}x{height} is empty"
            )));
        }
        if stride < width {
            return Err(CoreError::InvalidArgument(format!(
                "image stride {stride} is smaller than its width {width}"
            )));
        }
        let needed = (height - 1)
            .checked_mul(stride)
            .and_then(|n| n.checked_add(width))
            .ok_or_else(|| CoreError::InvalidArgument("image size overflows".into()))?;
        if data.len() < needed {
            return Err(CoreError::InvalidArgument(format!(
                "image buffer has {} bytes, {width}x{height} with stride {stride} needs {needed}",
                data.len()
            )));
        }
        Ok(Self {
            data,
            width,
            height,
            stride,
        })
    }

    /// Wraps a tightly packed `width` x `height` buffer (stride = width).
    pub fn from_packed(data: &'a [u8], width: usize, height: usize) -> Result<Self, CoreError> {
        Self::new(data, width, height, width)
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Distance between two rows, in bytes.
    pub fn stride(&self) -> usize {
        self.stride
    }

    /// The underlying bytes (rows `stride` apart; the last row may be exactly `width` long).
    pub fn data(&self) -> &'a [u8] {
        self.data
    }

    /// Row `y` (`width` pixels). Panics (debug and release) when `y >= height`.
    pub fn row(&self, y: usize) -> &'a [u8] {
        let start = y * self.stride;
        &self.data[start..start + self.width]
    }

    /// Pixel `(x, y)`, or `None` outside the image.
    pub fn get(&self, x: usize, y: usize) -> Option<u8> {
        if x < self.width && y < self.height {
            self.data.get(y * self.stride + x).copied()
        } else {
            None
        }
    }
}

/// An owned 8-bit gray image with a fixed capacity, reused from frame to frame.
///
/// Rows are `stride` bytes apart; `stride` is chosen at construction and never changes, so the
/// buffer is allocated once.
#[derive(Debug, Clone)]
pub struct GrayBuffer {
    data: Vec<u8>,
    width: usize,
    height: usize,
    stride: usize,
}

impl GrayBuffer {
    /// A zeroed `width` x `height` buffer with `stride` bytes per row (`stride >= width`).
    pub fn new(width: usize, height: usize, stride: usize) -> Result<Self, CoreError> {
        if width == 0 || height == 0 || stride < width {
            return Err(CoreError::InvalidArgument(format!(
                "buffer {width}x{height} with stride {stride} is invalid"
            )));
        }
        let len = height
            .checked_mul(stride)
            .ok_or_else(|| CoreError::InvalidArgument("buffer size overflows".into()))?;
        Ok(Self {
            data: vec![0; len],
            width,
            height,
            stride,
        })
    }

    /// A copy of `img`, packed (stride = width).
    pub fn from_image(img: &GrayImage<'_>) -> Self {
        let mut data = Vec::with_capacity(img.width() * img.height());
        for y in 0..img.height() {
            data.extend_from_slice(img.row(y));
        }
        Self {
            data,
            width: img.width(),
            height: img.height(),
            stride: img.width(),
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Distance between two rows, in bytes.
    pub fn stride(&self) -> usize {
        self.stride
    }

    /// All bytes (`height * stride`).
    pub fn data(&self) -> &[u8] {
        &self.data
    }

    /// All bytes, mutable.
    pub fn data_mut(&mut self) -> &mut [u8] {
        &mut self.data
    }

    /// A borrowed view of the buffer.
    pub fn view(&self) -> GrayImage<'_> {
        GrayImage {
            data: &self.data,
            width: self.width,
            height: self.height,
            stride: self.stride,
        }
    }

    /// Row `y`, mutable (`width` pixels). Panics when `y >= height`.
    pub fn row_mut(&mut self, y: usize) -> &mut [u8] {
        let start = y * self.stride;
        &mut self.data[start..start + self.width]
    }

    /// Changes the logical size without reallocating; errors if it does not fit the stride or
    /// the capacity chosen at construction.
    pub(crate) fn set_size(&mut self, width: usize, height: usize) -> Result<(), CoreError> {
        if width == 0
            || height == 0
            || width > self.stride
            || height * self.stride > self.data.len()
        {
            return Err(CoreError::InvalidArgument(format!(
                "size {width}x{height} does not fit a buffer of stride {} and {} bytes",
                self.stride,
                self.data.len()
            )));
        }
        self.width = width;
        self.height = height;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn view_checks_sizes() {
        let data = vec![0u8; 100];
        assert!(GrayImage::new(&data, 10, 10, 10).is_ok());
        assert!(GrayImage::new(&data, 10, 10, 9).is_err());
        assert!(GrayImage::new(&data, 10, 11, 10).is_err());
        assert!(GrayImage::new(&data, 0, 10, 10).is_err());
        // Last row may be short of the stride.
        assert!(GrayImage::new(&data, 8, 10, 11).is_err());
        assert!(GrayImage::new(&data, 8, 9, 11).is_ok());
    }

    #[test]
    fn view_indexing() {
        let data: Vec<u8> = (0..30).collect();
        let img = GrayImage::new(&data, 4, 3, 10).unwrap();
        assert_eq!(img.row(2), &[20, 21, 22, 23]);
        assert_eq!(img.get(3, 1), Some(13));
        assert_eq!(img.get(4, 1), None);
        let buf = GrayBuffer::from_image(&img);
        assert_eq!(buf.data(), &[0, 1, 2, 3, 10, 11, 12, 13, 20, 21, 22, 23]);
    }
}
