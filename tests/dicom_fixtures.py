"""A DICOM CT slice for the tests that write series (pydicom's Dataset, as a scanner writes it)."""

from __future__ import annotations

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid


def ct_slice(plane: np.ndarray, position, orientation=(1, 0, 0, 0, 1, 0), series: str = "1.2.3.4",
             spacing=(1.0, 1.0, 1.0), rescale=(1.0, 0.0), number: int = 1) -> Dataset:
    """A CT slice: ``plane`` is (rows, columns) int16; ``spacing`` (x, y, z)."""
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = CTImageStorage
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, ds.file_meta.MediaStorageSOPInstanceUID
    ds.Modality, ds.SeriesInstanceUID, ds.SeriesDescription, ds.SeriesNumber = "CT", series, "test", 3
    ds.InstanceNumber = number
    ds.Rows, ds.Columns = plane.shape
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.ImagePositionPatient = [float(p) for p in position]
    ds.ImageOrientationPatient = [float(o) for o in orientation]
    ds.PixelSpacing = [spacing[1], spacing[0]]  # between rows (y), between columns (x)
    ds.RescaleSlope, ds.RescaleIntercept = rescale
    ds.PixelData = np.ascontiguousarray(plane, dtype="<i2").tobytes()
    return ds
