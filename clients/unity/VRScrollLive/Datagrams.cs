// The live service's binary datagrams (protocol 4, docs/live.md "Datagrams"): a pose or pen sample out; a pen's
// reply, an approximation and its frame estimates in. Little-endian on the wire whatever the machine; nothing beyond the .NET base library.
using System;
using System.Collections.Generic;

namespace VRScroll.Live
{
    public static class Datagrams
    {
        public const int SampleBytes = 152;
        public const int PenReplyBytes = 104, EstimatesBytes = 40;
        public const byte Pose = 1, Pen = 2, PenRedirected = 3, Approximation = 4, Estimates = 5;  // the kind byte
        const byte HasT = 1, HasDevice = 2, Within = 2;  // flags

        /// A sample: kind Pose or Pen, the welcome's session as its 16 bytes, seq, t_s (s, this client's clock),
        /// position mm, quaternion w first; a pen may carry the tracked device's pose (both null otherwise).
        public static byte[] EncodeSample(byte kind, byte[] session, long seq, double tS, double[] position, double[] quat,
                                          double[] devicePosition, double[] deviceQuat)
        {
            var b = new byte[SampleBytes];
            b[0] = (byte)'V';
            b[1] = (byte)'S';
            b[2] = (byte)LiveClient.ProtocolVersion;
            b[3] = kind;
            b[4] = (byte)(HasT | (devicePosition != null ? HasDevice : 0));
            Buffer.BlockCopy(session, 0, b, 8, 16);
            PutLong(b, 24, seq);
            PutDouble(b, 32, tS);
            for (int k = 0; k < 3; k++) PutDouble(b, 40 + 8 * k, position[k]);
            for (int k = 0; k < 4; k++) PutDouble(b, 64 + 8 * k, quat[k]);
            if (devicePosition != null)
            {
                for (int k = 0; k < 3; k++) PutDouble(b, 96 + 8 * k, devicePosition[k]);
                for (int k = 0; k < 4; k++) PutDouble(b, 120 + 8 * k, deviceQuat[k]);
            }
            return b;
        }

        /// The reply in the first `length` bytes of b (a receive buffer: pen_redirected, approximation, estimates) as the
        /// fields docs/live.md names (numbers double, arrays List<object>, as Json gives them); FormatException if it is
        /// not one of this protocol's.
        public static Dictionary<string, object> DecodeReply(byte[] b, int length)
        {
            if (length < 24 || b[0] != 'V' || b[1] != 'S' || b[2] != LiveClient.ProtocolVersion)
                throw new FormatException("a reply of " + length + " bytes that is not one of this protocol's");
            int flags = b[4];
            var reply = new Dictionary<string, object> {
                { "seq", (double)GetLong(b, 8) }, { "t_s", (flags & HasT) != 0 ? (object)GetDouble(b, 16) : null } };
            if (b[3] == PenRedirected && length == PenReplyBytes)
            {
                reply["type"] = "pen_redirected";
                reply["position_mm"] = Doubles(b, 24, 3);
                reply["quat_wxyz"] = Doubles(b, 48, 4);
                reply["offset_mm"] = GetDouble(b, 80);
                reply["rotation_deg"] = GetDouble(b, 88);
                reply["height_mm"] = GetDouble(b, 96);
                reply["flap"] = (double)b[5];
                reply["within_thresholds"] = (flags & Within) != 0;
            }
            else if (b[3] == Approximation && length == 24 + 8 * (8 + b[5] + b[6]))
            {
                int hinges = b[5], flaps = b[6];
                reply["type"] = "approximation";
                reply["root_position_mm"] = Doubles(b, 24, 3);
                reply["root_quat_wxyz"] = Doubles(b, 48, 4);
                reply["angles_deg"] = Doubles(b, 80, hinges);
                reply["widths_mm"] = Doubles(b, 80 + 8 * hinges, flaps);
                reply["time_ms"] = GetDouble(b, 80 + 8 * (hinges + flaps));
            }
            else if (b[3] == Estimates && length == EstimatesBytes)
            {
                reply["type"] = "estimates";
                reply["msd_estimate_mm"] = GetDouble(b, 24);
                reply["share_within_estimate"] = GetDouble(b, 32);
            }
            else throw new FormatException("a reply of " + length + " bytes, kind " + b[3] + ": not one of this protocol's");
            return reply;
        }

        /// The welcome's session (32 hex digits) as the 16 bytes a sample carries.
        public static byte[] SessionBytes(string hex)
        {
            if (hex == null || hex.Length != 32) throw new FormatException("a session is 32 hex digits");
            var b = new byte[16];
            for (int k = 0; k < 16; k++) b[k] = Convert.ToByte(hex.Substring(2 * k, 2), 16);
            return b;
        }

        static List<object> Doubles(byte[] b, int at, int n)
        {
            var list = new List<object>(n);
            for (int k = 0; k < n; k++) list.Add(GetDouble(b, at + 8 * k));
            return list;
        }

        static void PutLong(byte[] b, int at, long v)
        {
            for (int k = 0; k < 8; k++) b[at + k] = (byte)(v >> (8 * k));
        }

        static void PutDouble(byte[] b, int at, double v)
        {
            PutLong(b, at, BitConverter.DoubleToInt64Bits(v));
        }

        static long GetLong(byte[] b, int at)
        {
            long v = 0;
            for (int k = 7; k >= 0; k--) v = (v << 8) | b[at + k];
            return v;
        }

        static double GetDouble(byte[] b, int at)
        {
            return BitConverter.Int64BitsToDouble(GetLong(b, at));
        }
    }
}
