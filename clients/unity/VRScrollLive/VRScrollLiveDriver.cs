// A MonoBehaviour that drives a VRScroll model in Unity from the live service (docs/live.md), through
// LiveClient. Unity only (it needs UnityEngine); the transport it uses is tested without Unity.
//
// Every frame: the tracked device's pose goes out; the newest approximation bends the model's hinges
// (before a lock), the morph's progress and its end bend them after; once done, the tracked pen goes out
// and the virtual pen is put where the service redirects it. The lock key stands in for the pen's switch.
//
// Frames: Unity is left-handed with y up, the service right-handed with z up (the target's frame, mm).
// Swapping y and z maps one onto the other (a reflection, so rotations change sense); the model's hinge
// joints are expected to turn about their local z (the device's hinge axis y, after the swap) with angle
// 0 flat, hinge 0 between flaps 0 and 1, each joint a child of the flap nearer the root (flap 3). The
// service's angles are about +y in the inner flap left of the root and about -y right of it (axisSign).
using System;
using System.Collections.Generic;
using UnityEngine;
using VRScroll.Live;

public class VRScrollLiveDriver : MonoBehaviour
{
    public string serviceUrl = "ws://127.0.0.1:8765";
    public string token = "";
    public string shape = "cylinder";
    public Transform trackedDevice;  // the device's anchor (the root flap's touch surface centre), tracked
    public Transform pen;  // the tracked pen tip, its forward axis along the pen
    public Transform virtualPen;  // drawn where the service redirects the pen
    public Transform[] hinges = new Transform[6];
    public float[] axisSign = { 1, 1, 1, -1, -1, -1 };
    public KeyCode lockKey = KeyCode.Space;

    LiveClient client;
    bool penLive;

    async void Start()
    {
        client = new LiveClient(new Uri(serviceUrl), "control", token == "" ? null : token);
        try
        {
            await client.ConnectAsync();
            await client.SetTargetAsync(shape);
        }
        catch (Exception e)
        {
            Debug.LogError("VRScroll live service: " + e.Message);
            client = null;
        }
    }

    void Update()
    {
        if (client == null || client.Welcome == null) return;
        client.SendPose(ToService(trackedDevice.position), ToService(trackedDevice.rotation));
        if (Input.GetKeyDown(lockKey))
        {
            penLive = false;
            var sent = client.LockAsync();
        }
        var approximation = client.LatestApproximation;
        if (approximation != null && !penLive) Bend(approximation);
        Dictionary<string, object> ev;
        while (client.TryGetEvent(out ev))
        {
            var type = (string)ev["type"];
            if (type == "progress" || type == "done") Bend(ev);
            if (type == "done") penLive = true;
            if (type == "refused" || type == "stopped" || type == "error") Debug.LogWarning("VRScroll " + type + ": " + ev["message"]);
        }
        if (!penLive || pen == null) return;
        client.SendPen(ToService(pen.position), ToService(pen.rotation));
        Dictionary<string, object> reply, newest = null;
        while (client.TryGetPen(out reply)) newest = reply;
        if (newest != null && virtualPen != null)
        {
            virtualPen.position = FromServicePosition(Json.Numbers(newest["position_mm"]));
            virtualPen.rotation = FromServiceRotation(Json.Numbers(newest["quat_wxyz"]));
        }
    }

    void Bend(Dictionary<string, object> message)
    {
        var degrees = Json.Numbers(message["angles_deg"]);
        for (int k = 0; k < hinges.Length && k < degrees.Length; k++)
            if (hinges[k] != null) hinges[k].localRotation = Quaternion.AngleAxis(-axisSign[k] * (float)degrees[k], Vector3.forward);
    }

    void OnDestroy()
    {
        if (client != null) client.Dispose();
    }

    static double[] ToService(Vector3 p)
    {
        return new double[] { p.x * 1000.0, p.z * 1000.0, p.y * 1000.0 };
    }

    static double[] ToService(Quaternion q)
    {
        return new double[] { q.w, -q.x, -q.z, -q.y };
    }

    static Vector3 FromServicePosition(double[] mm)
    {
        return new Vector3((float)(mm[0] / 1000.0), (float)(mm[2] / 1000.0), (float)(mm[1] / 1000.0));
    }

    static Quaternion FromServiceRotation(double[] q)
    {
        return new Quaternion(-(float)q[1], -(float)q[3], -(float)q[2], (float)q[0]);
    }
}
